"""Global descriptors for retrieval, computed from the network's coarsest feature map: the
registry ``DESCRIPTORS`` (``FeatureConfig.descriptor`` and ``build-map --descriptor`` choose one).

An entry is a settings dataclass: ``dim(channels)`` is the length of its descriptor (the store's
``global`` array), ``__call__(features)`` computes it from a (C, H, W) tensor, L2-normalised.
Importing this module imports no torch: a store's schema checks names and sizes without it.
A new descriptor is one class here.
"""

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


DEFAULT_DESCRIPTOR = GeM.name


def global_descriptor(features, kind: str = DEFAULT_DESCRIPTOR):
    """The global descriptor ``kind`` of a (C, H, W) feature map."""
    return DESCRIPTORS.entry(kind)()(features)
