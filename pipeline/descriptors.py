"""Global descriptors for retrieval, computed from the network's coarsest feature map: the
registry ``DESCRIPTORS`` (``FeatureConfig.descriptor`` and ``build-map --descriptor`` choose one).

An entry is a settings dataclass: ``dim(channels)`` is the length of its descriptor (the store's
``global`` array), ``__call__(features)`` computes it from a (C, H, W) tensor, L2-normalised.
Importing this module imports no torch: a store's schema checks names and sizes without it.
A new descriptor is one class here.
"""

import functools
from dataclasses import dataclass
from typing import ClassVar, Tuple

from pipeline.registry import Registry

DESCRIPTORS = Registry("global descriptor")


@DESCRIPTORS.register("gem")
@dataclass(frozen=True)
class GeM:
    """Generalised-mean pooling (Radenovic et al. 2018), exponent ``p``."""

    p: float = 3.0
    help: ClassVar[str] = "gem pooling"

    def dim(self, channels: int) -> int:
        return channels

    def __call__(self, features):
        from torch.nn.functional import normalize
        pooled = features.clamp(min=1e-6).pow(self.p).mean((-2, -1)).pow(1 / self.p)
        return normalize(pooled, dim=0)


@DESCRIPTORS.register("grid")
@dataclass(frozen=True)
class Grid:
    """Per-cell means over a ``grid`` of the features less their image mean: keeps the layout,
    more robust to changes of light in our synthetic tests."""

    grid: Tuple[int, int] = (2, 3)
    help: ClassVar[str] = "a 2x3 grid of mean-centred features"

    def dim(self, channels: int) -> int:
        return channels * self.grid[0] * self.grid[1]

    def __call__(self, features):
        from torch.nn.functional import adaptive_avg_pool2d, normalize
        cells = adaptive_avg_pool2d(features[None], self.grid)[0]
        cells = normalize(cells - cells.mean((1, 2), keepdim=True), dim=0)
        return normalize(cells.reshape(-1), dim=0)


@DESCRIPTORS.register("gem-lw")
@dataclass(frozen=True)
class WhitenedGeM:
    """``gem`` with a learned whitening (Radenovic et al. 2018): normalise(P (gem - mean)), P and
    mean learned in closed form from posed images and their relit copies (``pixloc train-whitening``).
    ``whitening``: its npz file (default: the shipped one, learned on pixloc-lite0's features; which
    scenes trained it is in docs/model_card.md)."""

    whitening: str = ""
    help: ClassVar[str] = "gem with a whitening learned on posed images (pixloc-lite0's features)"

    def dim(self, channels: int) -> int:
        return channels

    def __call__(self, features):
        import torch
        return torch.from_numpy(whiten(GeM()(features).cpu().numpy(), self.whitening)).to(features.device)


def shipped_whitening() -> str:
    from importlib import resources
    return str(resources.files("pixloc.nets") / "weights" / "pixloc-lite0.gem-lw.npz")


def whitening(path: str = ""):
    """(mean, projection) of a whitening file (``WhitenedGeM``), read once per process."""
    return _read_whitening(path or shipped_whitening())


@functools.lru_cache(maxsize=4)
def _read_whitening(path: str):
    import numpy as np
    with np.load(path, allow_pickle=False) as z:
        return z["mean"].astype(np.float32), z["projection"].astype(np.float32)


def whiten(gem, path: str = ""):
    """``gem`` descriptors (..., C), L2-normalised, whitened and normalised again (numpy)."""
    import numpy as np
    mean, projection = whitening(path)
    if gem.shape[-1] != len(mean):
        raise ValueError(f"the whitening {path or shipped_whitening()} is for {len(mean)}-channel features, "
                         f"not {gem.shape[-1]}: it was learned on another model's.")
    out = (np.asarray(gem, np.float32) - mean) @ projection.T
    return out / np.maximum(np.linalg.norm(out, axis=-1, keepdims=True), 1e-12)


DEFAULT_DESCRIPTOR = WhitenedGeM.name  # chosen by ``pixloc benchmark retrieval`` (docs/benchmarks.md, "Retrieval")
UNNAMED_DESCRIPTOR = GeM.name  # the one that a store's feature key and an old config record leave unnamed


def global_descriptor(features, kind: str):
    """The global descriptor ``kind`` of a (C, H, W) feature map."""
    return DESCRIPTORS.entry(kind)()(features)
