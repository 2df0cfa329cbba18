"""Which image pairs SIFT matching compares when a map is triangulated or reconstructed.

Exhaustive matching is O(n^2) pairs: fine for a few dozen images, hours for thousands.
Above ``exhaustive_below`` images the ``auto`` method picks a scalable one:

- ``spatial`` (known poses): each image with its ``num_neighbors`` nearest camera centres
  among those whose optical axes differ by less than ``max_angle`` degrees (frusta that can
  overlap); matched with pycolmap's ``match_image_pairs``.
- ``sequential`` (ordered frames): the next ``overlap`` images in name order and those 2**k
  ahead (COLMAP's sequential pairing).
- ``retrieval`` (unposed, unordered): the top ``num_neighbors`` of each image by cosine
  similarity of global descriptors (of the network's coarsest features, as build-map's default).
- ``file``: an hloc pairs file (``name0 name1`` per line), as given.

Pairs are written to ``pairs.txt`` in the work folder, so a user can see what was matched;
``pipeline.mapping.structure`` matches them in chunks.
"""

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np

from pipeline.regions import camera_centres
from pipeline.textfiles import read_text

logger = logging.getLogger(__name__)

METHODS = ("auto", "exhaustive", "spatial", "sequential", "retrieval", "file")
Pair = Tuple[str, str]


@dataclass(frozen=True)
class PairsConfig:
    """How image pairs are chosen (see the module docstring)."""

    method: str = "auto"
    num_neighbors: int = 10
    max_angle: float = 90.0
    overlap: int = 10
    exhaustive_below: int = 60
    path: Optional[str] = None

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"Unknown pairs method {self.method!r}; known: {', '.join(METHODS)}.")
        if self.method == "file" and not self.path:
            raise ValueError("Pairs method 'file' needs a pairs file (--pairs-file).")
        if self.num_neighbors < 1 or self.overlap < 1:
            raise ValueError("num_neighbors and overlap must be >= 1.")

    def resolve(self, num_images: int, posed: bool) -> str:
        """The method ``auto`` stands for with ``num_images`` images (``posed``: known poses)."""
        if self.method != "auto":
            return self.method
        if self.path:
            return "file"
        if num_images < self.exhaustive_below:
            return "exhaustive"
        return "spatial" if posed else "retrieval"


def _unique(pairs) -> List[Pair]:
    seen, out = set(), []
    for a, b in pairs:
        key = (a, b) if a < b else (b, a)
        if a != b and key not in seen:
            seen.add(key)
            out.append(key)
    return out


def exhaustive_pairs(names: Sequence[str]) -> List[Pair]:
    """Every pair of images, once."""
    return [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]


def spatial_pairs(names: Sequence[str], cam_from_world: Sequence[np.ndarray], num_neighbors: int = 10,
                  max_angle: float = 90.0) -> List[Pair]:
    """Each image with its ``num_neighbors`` nearest camera centres among the images whose
    optical axes are within ``max_angle`` degrees of its own."""
    T = np.asarray(cam_from_world, np.float64)
    centres = camera_centres(T)
    axes = T[:, 2, :3]  # the camera z axis in world coordinates
    cos_max = np.cos(np.radians(max_angle))
    pairs = []
    for i in range(len(names)):
        d = np.linalg.norm(centres - centres[i], axis=1)
        d[i] = np.inf
        d[axes @ axes[i] < cos_max] = np.inf
        for j in np.argsort(d, kind="stable")[:num_neighbors]:
            if np.isfinite(d[j]):
                pairs.append((names[i], names[j]))
    return _unique(pairs)


def retrieval_pairs(names: Sequence[str], descriptors: np.ndarray, num_neighbors: int = 10) -> List[Pair]:
    """Each image with its top ``num_neighbors`` others by cosine similarity of (L2-normalised)
    global descriptors."""
    D = np.asarray(descriptors, np.float32)
    sim = D @ D.T
    np.fill_diagonal(sim, -np.inf)
    k = min(num_neighbors, len(names) - 1)
    pairs = []
    for i in range(len(names)):
        for j in np.argsort(-sim[i], kind="stable")[:k]:
            pairs.append((names[i], names[j]))
    return _unique(pairs)


def read_pairs(path, names: Sequence[str]) -> List[Pair]:
    """An hloc pairs file; a line that is not two names, or a name not among ``names``, is an error
    that names the line."""
    known = set(names)
    pairs = []
    for n, line in enumerate(read_text(path, "pairs file").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2:
            raise ValueError(f"{path}:{n}: expected 'name0 name1', got {line!r}.")
        missing = [p for p in parts if p not in known]
        if missing:
            raise ValueError(f"{path}:{n}: image {missing[0]!r} is not among the map's {len(names)} images.")
        pairs.append((parts[0], parts[1]))
    if not pairs:
        raise ValueError(f"{path} lists no image pairs.")
    return _unique(pairs)


def write_pairs(pairs: Sequence[Pair], path) -> Path:
    path = Path(path)
    path.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    return path


def image_descriptors(paths: Sequence[Path], model: str, resize: int = 320) -> np.ndarray:
    """Global descriptors of the network's coarsest features at a small size (for ``retrieval``): the
    descriptor that build-map gives this model's maps (``gem-lw`` for the shipped model, else ``gem``)."""
    import torch

    from pipeline.models import network
    from pipeline.mapping.features import FeatureConfig, global_descriptor
    from pipeline.images import read_image, resize_max, to_tensor
    net, _ = network(model)
    kind = FeatureConfig(model=model).descriptor
    out = []
    with torch.inference_mode():
        for p in paths:
            image, _ = resize_max(read_image(p), resize)
            out.append(global_descriptor(net(to_tensor(image)[None])["features"][-1][0], kind).numpy())
    return np.stack(out)


def sequential_pairs(names: Sequence[str], overlap: int = 10) -> List[Pair]:
    """Each image with the next ``overlap`` ones in name order and those ``2**k`` ahead for
    ``k < overlap``: COLMAP's sequential pairing with its quadratic overlap (loop detection off)."""
    ordered = sorted(names)
    pairs = []
    for i, a in enumerate(ordered):
        ahead = {i + k + 1 for k in range(overlap)} | {i + (1 << k) for k in range(overlap)}
        pairs += [(a, ordered[j]) for j in sorted(ahead) if j < len(ordered)]
    return _unique(pairs)


def select_pairs(names: Sequence[str], conf: PairsConfig, *, cam_from_world: Optional[Sequence[np.ndarray]] = None,
                 image_dir: Optional[Path] = None, model: Optional[str] = None) -> List[Pair]:
    """The image pairs that ``conf`` matches among ``names`` (``cam_from_world``: known poses, if any;
    ``image_dir`` and ``model`` for ``retrieval``)."""
    method = conf.resolve(len(names), cam_from_world is not None)
    if method == "exhaustive":
        return exhaustive_pairs(names)
    if method == "sequential":
        return sequential_pairs(names, conf.overlap)
    if method == "spatial":
        if cam_from_world is None:
            raise ValueError("Pairs method 'spatial' needs known poses; use 'retrieval' or 'sequential'.")
        return spatial_pairs(names, cam_from_world, conf.num_neighbors, conf.max_angle)
    if method == "retrieval":
        if image_dir is None or model is None:
            raise ValueError("Pairs method 'retrieval' needs the images and a network.")
        return retrieval_pairs(names, image_descriptors([Path(image_dir) / n for n in names], model),
                               conf.num_neighbors)
    return read_pairs(conf.path, names)
