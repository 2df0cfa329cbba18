"""The finest level's query maps decoded where the LM and verification read them.

At 1,024 px the decoder blocks that only the finest level reads (at strides 2 and 1) are most of a
query's network time, and the LM samples the finest map only near its points' projections: about a third
of its 8 x 8 px tiles over the CPU benchmark's queries. A query's pass therefore stops before those blocks
(``pixloc.nets.unet.FinestMaps``, which decodes the map at stride 2 where the finest tiles read it), and
``FinestFill`` decodes the tiles around the points that a sampling of the maps is about to read
(``FeaturemetricProblem.maps_at``), into the query-maps buffer of the level's LM batch. The values are
those of the whole map to float rounding. Cells not decoded are left as allocated: writing NaN into them
(``FinestFill.poison``, which the tests turn on to show that no read bypasses the fill) cost a query 35 ms
per 90 MB map, most of it the first touch of pages that nothing else reads.
"""

from typing import Dict, Optional, Tuple

import torch
from torch import Tensor

from pipeline.runtime import poison_undecoded
from pixloc.nets.unet import TILE, FinestMaps, tile_cells, write_cells

# a first request for more than this fraction of a map's tiles decodes the whole map in one pass,
# cheaper per pixel than tiles with their context (docs/benchmarks.md, "The CPU query")
WHOLE_ABOVE = 0.5
CHUNK = 1024  # tiles decoded in one network call


def write_level(maps: Tensor, features: Tensor, confidences: Optional[Tensor]) -> None:
    """Write one query's level into its rows of a query-maps buffer ``maps`` (C + 1, H, W): the
    features (C, H, W) L2-normalised per pixel (as official PixLoc's dense maps) and the confidence
    (1, H, W) (None: models without confidences weigh every pixel the same)."""
    torch.div(features, torch.linalg.vector_norm(features, dim=0, keepdim=True).clamp_min(1e-12), out=maps[:-1])
    maps[-1] = confidences[0] if confidences is not None else 1.0


def level_shape(pred: Dict, level: int) -> Tuple[int, ...]:
    """The shape (B, C, H, W) of a prediction's features at ``level``, deferred or not."""
    maps = pred["features"][level]
    return tuple(maps.shape) if maps is not None else tuple(pred["finest"].shape)


def level_like(pred: Dict, level: int) -> Tensor:
    """A tensor of a prediction's device and memory layout at ``level`` (``new_query_maps``; for a deferred
    level, the map before its deferred blocks)."""
    maps = pred["features"][level]
    return maps if maps is not None else pred["finest"].source


class Decoded:
    """One query's finest level, normalised, as far as it is decoded (kept with its ``FinestMaps`` in the
    query's cache, so that its starts, rivals and verification share the tiles): the decoded tiles'
    pixels, a row each (``values``), and ``tiles`` the count decoded. Only decoded tiles are held: about
    a third of a 1,024 px map at Cambridge settings."""

    def __init__(self, finest: FinestMaps):
        _, C, H, W = finest.shape
        self.finest, self.size = finest, (H, W)
        self.slot = torch.full(finest.grid, -1, dtype=torch.long)  # per tile: its block of ``data``, or -1
        self.data = torch.empty(0, TILE * TILE, C + 1, device=finest.source.device)
        self.tiles = 0

    @classmethod
    def of(cls, finest: FinestMaps) -> "Decoded":
        """The query's ``Decoded``, made on first use."""
        if finest.decoded is None:
            finest.decoded = cls(finest)
        return finest.decoded

    def decode(self, ids: Tensor) -> None:
        """Decode the tiles ``ids`` (flat indices into the tile grid) not decoded yet; a first request
        for more than ``WHOLE_ABOVE`` of them decodes the whole map in one pass (cheaper per pixel)."""
        ids = ids[self.slot.view(-1)[ids] < 0]
        if len(ids) == 0:
            return
        (H, W), (down, across) = self.size, self.slot.shape
        if self.tiles == 0 and len(ids) > WHOLE_ABOVE * self.slot.numel():
            features, confidences = self.finest.full()
            C = features.shape[1]
            whole = features.new_zeros(down * TILE, across * TILE, C + 1)  # a row per pixel, tiles padded
            write_level(whole[:H, :W].permute(2, 0, 1), features[0], None if confidences is None else confidences[0])
            ids = torch.arange(self.slot.numel())
            values = whole.view(down, TILE, across, TILE, C + 1).transpose(1, 2).reshape(-1, TILE * TILE, C + 1)
            self._append(ids, values)
            return
        for chunk in ids.split(CHUNK):  # the tiles' intermediate maps, ~25 KB a tile, a chunk at a time
            features, confidences = self.finest.tiles(chunk // across, chunk % across)
            n, C = features.shape[:2]
            values = torch.empty(n, TILE, TILE, C + 1, device=features.device)  # a row per pixel
            write_level(values.permute(3, 0, 1, 2), features.transpose(0, 1), None if confidences is None
                        else confidences.transpose(0, 1))
            self._append(chunk, values.view(n, TILE * TILE, C + 1))

    def _append(self, ids: Tensor, values: Tensor) -> None:
        need = self.tiles + len(ids)
        if need > len(self.data):  # room for twice as many: appending stays linear
            grown = self.data.new_empty((max(need, 2 * len(self.data)),) + tuple(self.data.shape[1:]))
            grown[:self.tiles] = self.data[:self.tiles]
            self.data = grown
        self.data[self.tiles:need] = values
        self.slot.view(-1)[ids] = torch.arange(self.tiles, need)
        self.tiles = need

    def values(self, ids: Tensor) -> Tensor:
        """The pixels of decoded tiles ``ids``, a row each, tile by tile in row order (``tile_cells``)."""
        return self.data.index_select(0, self.slot.view(-1)[ids].to(self.data.device)).reshape(-1, self.data.shape[-1])


class FinestFill:
    """``FeaturemetricProblem.fill`` for a batch whose rows ``finest`` (row -> ``FinestMaps``) have
    their finest level deferred: their rows of ``maps`` (B, C + 1, H, W) get the query's decoded tiles
    (``Decoded``) where they are sampled; the rest of them is left as allocated, or NaN with ``poison``
    (the test suite sets ``PIXLOC_POISON_UNDECODED`` to 1, for its worker processes too: a read that bypassed the fill
    is then NaN, not features)."""

    poison = poison_undecoded()

    def __init__(self, maps: Tensor, finest: Dict[int, FinestMaps]):
        self.maps, self.decoded = maps, {b: Decoded.of(f) for b, f in finest.items()}
        self.done = {b: torch.zeros(f.grid, dtype=torch.bool) for b, f in finest.items()}
        for b in finest if self.poison else ():
            maps[b].fill_(float("nan"))

    def __call__(self, p2d: Tensor, rows, gradients: bool = True) -> None:
        """Decode the cells of rows ``rows`` that sampling at ``p2d`` reads: with the official central
        differences (``gradients``), or values only (verification's costs around a pose)."""
        for j, b in enumerate(rows):
            if b in self.decoded:
                self._fill(b, p2d[j], gradients)

    @torch.no_grad()
    def _fill(self, b: int, p2d: Tensor, gradients: bool = True) -> None:
        done = self.done[b]
        if bool(done.all()):
            return
        H, W = self.maps.shape[-2:]
        p = p2d.detach().cpu()
        p = p[torch.isfinite(p).all(-1)]
        x0, y0 = p[:, 0].floor(), p[:, 1].floor()
        # a bilinear sample with central differences at +-1 px reads cells x0 - 1 .. x0 + 2, y0 - 1 .. y0 + 2,
        # a value alone x0 .. x0 + 1, y0 .. y0 + 1
        lo, hi = (1, 2) if gradients else (0, 1)
        near = (x0 + hi >= 0) & (x0 - lo <= W - 1) & (y0 + hi >= 0) & (y0 - lo <= H - 1)
        x0, y0 = x0[near], y0[near]
        tx = torch.stack([(x0 - lo).clamp(0, W - 1), (x0 + hi).clamp(0, W - 1)]).long() // TILE
        ty = torch.stack([(y0 - lo).clamp(0, H - 1), (y0 + hi).clamp(0, H - 1)]).long() // TILE
        wanted = torch.zeros(done.numel(), dtype=torch.bool)  # the tiles read, marked: sorted ids without a sort
        wanted[(ty[:, None] * done.shape[1] + tx[None]).reshape(-1)] = True
        ids = (wanted & ~done.view(-1)).nonzero()[:, 0]
        if len(ids) == 0:
            return
        decoded = self.decoded[b]
        decoded.decode(ids)
        across = done.shape[1]
        pixels, inside = tile_cells(ids // across, ids % across, H, W)
        values = decoded.values(ids)
        write_cells(self.maps[b], pixels, values if inside is None else values[inside])
        done.view(-1)[ids] = True


FinestMaps.poison = FinestFill.poison  # the network's decode too, in every process that localizes
