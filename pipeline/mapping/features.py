"""Reference features at map-point observations, sampled as the official localizer samples them.

For each image scale (official ``multiscale``: target size = resize // s),
the image is downscaled so that its longer side is at most the target, the
network runs once, and every level's raw (not normalised) features and
confidence are bilinearly sampled at the projection of each 3D point the
image observes, with the level's camera. An observation is valid at a level
when it projects inside the image and inside the interpolation margin.
"""

import logging
from dataclasses import asdict, dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from pixloc.interpolation import Interpolator
from pixloc.nets.registry import DEFAULT_MODEL
from pixloc.nets.unet import UNet

from pipeline.images import read_image_for, resize_max, to_tensor
from pipeline.keypoints import MAX_FEATURES, MAX_GAP, extract_sift, observation_descriptors
from pipeline.scene import ImageRecord

logger = logging.getLogger(__name__)


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
    descriptor: global descriptor for retrieval, from the coarsest feature map: ``gem``
        (generalised mean) or ``grid`` (mean-centred features averaged over a 2 x 3 grid:
        keeps the layout, more robust to changes of light in our synthetic tests).
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
    descriptor: str = "gem"
    pca: Optional[int] = None  # 48 with int8, else 0
    sift: int = 0

    def __post_init__(self):
        if self.pca is None:
            object.__setattr__(self, "pca", COMPACT_PCA if self.dtype == "int8" else 0)
        if self.dtype not in DTYPES:
            raise ValueError(f"Unknown feature storage type {self.dtype!r}; known: {', '.join(DTYPES)}.")
        if self.descriptor not in DESCRIPTORS:
            raise ValueError(f"Unknown global descriptor {self.descriptor!r}; known: {', '.join(DESCRIPTORS)}.")
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
        made before them, or without them), not the default."""
        d = {"pca": 0, "sift": 0, **d}
        return cls(**{**d, "image_scales": tuple(d.get("image_scales", cls.image_scales))})

    def to_dict(self) -> Dict:
        d = asdict(self)
        d["image_scales"] = list(self.image_scales)
        for key in ("pca", "sift"):  # stores made before these options have no such keys
            if not d[key]:
                del d[key]
        return d

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


def gem(features: torch.Tensor, p: float = 3.0) -> torch.Tensor:
    """Generalised-mean pooling (Radenovic et al. 2018) of (C, H, W) -> L2-normalised (C,)."""
    pooled = features.clamp(min=1e-6).pow(p).mean((-2, -1)).pow(1 / p)
    return torch.nn.functional.normalize(pooled, dim=0)


def grid_descriptor(features: torch.Tensor, grid=(2, 3)) -> torch.Tensor:
    """(C, H, W) -> L2-normalised (C * 6,): per-cell means of the features less their image mean."""
    cells = torch.nn.functional.adaptive_avg_pool2d(features[None], grid)[0]
    cells = torch.nn.functional.normalize(cells - cells.mean((1, 2), keepdim=True), dim=0)
    return torch.nn.functional.normalize(cells.reshape(-1), dim=0)


DESCRIPTORS = {"gem": gem, "grid": grid_descriptor}


def global_descriptor(features: torch.Tensor, kind: str = "gem") -> torch.Tensor:
    """The global descriptor ``kind`` of a (C, H, W) feature map."""
    return DESCRIPTORS[kind](features)


@torch.no_grad()
def extract_image_features(net: UNet, conf: FeatureConfig, image: ImageRecord, p3d_world: np.ndarray,
                           device: str = "cpu") -> ImageFeatures:
    """Sample the features of ``image`` at the projections of ``p3d_world`` (K, 3)."""
    rgb, camera, note = read_image_for(image.path, image.camera)  # the same size rule as queries
    if note:
        logger.warning("Map image %s: %s", image.name, note)
    camera = camera.to_pixloc(torch.float64)
    p3d_cam = image.pose(torch.float64).transform(torch.from_numpy(np.asarray(p3d_world, np.float64)))
    interpolator = Interpolator("linear", conf.pad)
    samples, descriptor = {}, None
    for k, image_scale in enumerate(conf.image_scales):
        resized, (sx, sy) = resize_max(rgb, conf.resize // image_scale)
        pred = net(to_tensor(resized)[None].to(device))
        for level, stride in enumerate(net.strides):
            cam = camera.scale((sx / stride, sy / stride))
            p2d, visible = cam.cam2image(p3d_cam)
            fmap = pred["features"][level][0]
            values, inside, _ = interpolator(fmap, p2d.to(fmap))
            conf_map = pred["confidences"][level][0] if "confidences" in pred else torch.ones_like(fmap[:1])
            confidence, _, _ = interpolator(conf_map, p2d.to(fmap))
            samples[(k, level)] = (values.cpu().numpy(), confidence[:, 0].cpu().numpy(),
                                   (inside & visible.to(inside.device)).cpu().numpy())
        if image_scale == 1 or k == len(conf.image_scales) - 1:
            descriptor = global_descriptor(pred["features"][-1][0], conf.descriptor).cpu().numpy()
    sift = None
    if conf.sift:  # keypoints and observations in the pixels of the image read (COLMAP convention)
        p2d, visible = camera.cam2image(p3d_cam)
        observed = np.where(visible.numpy()[:, None], p2d.numpy() + 0.5, np.nan)
        sift = observation_descriptors(*extract_sift(rgb, conf.sift, MAX_FEATURES), observed, MAX_GAP)
    return ImageFeatures(samples, descriptor, sift)

