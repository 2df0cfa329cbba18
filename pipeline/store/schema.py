"""The schema of a map store's feature groups: ``FeatureConfig``, the settings a group was
extracted with, recorded in its attributes and checked on reuse. Importing it imports no torch:
reading a store needs no network.
"""

from dataclasses import asdict, dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from pixloc import DEFAULT_MODEL
from pipeline.descriptors import DEFAULT_DESCRIPTOR, DESCRIPTORS, UNNAMED_DESCRIPTOR
from pipeline.settings import parse

DTYPES = ("float16", "int8", "float32")
COMPACT_PCA = 48  # the default store's components per level, with int8 (docs/benchmarks.md, feature storage)


@dataclass(frozen=True)
class FeatureConfig:
    """How reference features are extracted; stored with them and checked on reuse.

    model: network name or checkpoint path (see ``pixloc.nets.registry``; default the
        shipped ``pixloc-lite0``).
    resize: longer image side in pixels at image scale 1 (images are only downscaled).
    image_scales: official ``multiscale`` factors, coarse first (e.g. (4, 1)).
    pad: interpolation margin in feature-map pixels (official ``pad``).
    dtype: storage type of features, ``int8`` (default: a quarter of float32, codes with a
        float16 scale per row and level; with the PCA below, the compact store, whose recall
        docs/benchmarks.md compares with float16 on every real scene), ``float16`` (every
        channel in half precision: ``--dtype float16``) or ``float32`` (bit-exact with
        extraction, for parity studies). Confidences are float16 unless ``float32``.
    descriptor: global descriptor for retrieval, from the coarsest feature map: ``gem-lw``
        (default with the shipped model: generalised mean with a whitening learned on posed images
        and their relit copies, ``pixloc train-whitening``), ``gem`` (generalised mean; the default
        with another model, whose features the shipped whitening was not learned on) or ``grid``
        (mean-centred features averaged over a 2 x 3 grid: keeps the layout).
    pca: 0 stores every channel; D > 0 stores the levels with more than D channels as their D
        leading principal components (a PCA of the map's own features, fitted on a sample of
        its images when the feature group is created, stored with it); readers reconstruct the
        full channels. Default (None): 48 with int8, else 0, so ``--dtype float16`` alone gives
        the full float16 store. With int8, two image scales fit in about 300 bytes per
        observation (docs/map_store.md).
    sift: 0 (default) stores no local features; N > 0 also stores, per observation, the SIFT
        descriptor (extracted at a longer side of N pixels, 4,096 per image) of the keypoint
        within 2 pixels of it, for the ``sift`` prior (128 bytes per observation; zeros where no
        keypoint is near).
    """

    model: str = DEFAULT_MODEL
    resize: int = 1024
    image_scales: Tuple[int, ...] = (4, 1)
    pad: int = 2
    dtype: str = "int8"
    descriptor: Optional[str] = None  # gem-lw with the shipped model, else gem
    pca: Optional[int] = None  # 48 with int8, else 0
    sift: int = 0

    def __post_init__(self):
        if self.pca is None:
            object.__setattr__(self, "pca", COMPACT_PCA if self.dtype == "int8" else 0)
        if self.descriptor is None:  # the shipped whitening was learned on the shipped model's features
            object.__setattr__(self, "descriptor", DEFAULT_DESCRIPTOR if self.model == DEFAULT_MODEL
                               else UNNAMED_DESCRIPTOR)
        if self.dtype not in DTYPES:
            raise ValueError(f"Unknown feature storage type {self.dtype!r}; known: {', '.join(DTYPES)}.")
        DESCRIPTORS.entry(self.descriptor)  # an unknown one is refused with the known ones
        if self.pca < 0:
            raise ValueError(f"pca must be 0 (off) or a number of components, not {self.pca}.")
        if not self.image_scales or min(self.image_scales) < 1 or len(set(self.image_scales)) < len(self.image_scales):
            raise ValueError(f"image_scales must be distinct factors of at least 1 (e.g. 4 1), not "
                             f"{list(self.image_scales)}.")
        if self.resize // max(self.image_scales) < 16 or self.pad < 0:
            raise ValueError(f"resize ({self.resize} px) must leave at least 16 px at the coarsest image scale "
                             f"({max(self.image_scales)}), and pad ({self.pad}) must not be negative.")
        if self.sift and self.sift < 64:
            raise ValueError(f"sift must be 0 (off) or a longer image side of at least 64 pixels, not {self.sift}.")

    @classmethod
    def from_dict(cls, d: Dict) -> "FeatureConfig":
        """The config a store recorded (``to_dict``): an absent ``pca`` or ``sift`` is 0 (stores
        made before them, or without them), an absent ``descriptor`` is ``gem`` (before ``gem-lw``
        became the default), not the default."""
        return parse(cls, {"pca": 0, "sift": 0, "descriptor": UNNAMED_DESCRIPTOR, **d}, "feature config")

    def to_dict(self) -> Dict:
        d = asdict(self)
        d["image_scales"] = list(self.image_scales)
        return d

    def made(self, recorded) -> bool:
        """Whether a group whose attributes record ``recorded`` (``to_dict`` of this or an earlier
        version) was made with this config."""
        try:
            return isinstance(recorded, dict) and type(self).from_dict(recorded) == self
        except (ValueError, TypeError):
            return False

    def stored_dims(self, dims: List[int]) -> List[int]:
        """The channels stored per level for a network of ``dims`` channels per level."""
        return [min(d, self.pca) if self.pca else d for d in dims]


@dataclass
class ImageFeatures:
    """Samples for one image: per (scale, level), features (K, C) float32,
    confidences (K,), valid (K,); and a global descriptor (D,)."""

    samples: Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray, np.ndarray]]
    global_descriptor: np.ndarray
    sift: Optional[np.ndarray] = None  # (K, 128) uint8 per observation, with FeatureConfig.sift
