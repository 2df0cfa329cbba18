"""Sub-pixel interpolation of dense maps, with spatial gradients and validity.

Pixel coordinates have their origin at the centre of the top-left pixel.
"""

from typing import Callable, Optional, Tuple

import torch
from torch import Tensor
from torch.nn.functional import grid_sample


def mask_in_image(p2d: Tensor, size: Tensor, pad: int) -> Tensor:
    """(..., N) True where p2d (..., N, 2) lies in [pad, size - 1 - pad]; size: (..., 2) = (w, h)."""
    return ((p2d >= pad) & (p2d <= size[..., None, :] - 1 - pad)).all(-1)


def _bilinear(maps: Tensor, p2d: Tensor, gradients: bool) -> Tuple[Tensor, Optional[Tensor]]:
    """The official sampler: grid_sample (align_corners=True) on coordinates
    clamped to twice the map, and gradients by central differences at +-1 px.
    maps: B x C x H x W, p2d: B x N x 2 -> B x N x C, B x N x C x 2."""
    b, c, h, w = maps.shape
    scale = p2d.new_tensor([w - 1, h - 1])
    grid = ((p2d / scale) * 2 - 1).clamp(min=-2, max=2)
    n = grid.shape[1]
    if gradients:
        dx = p2d.new_tensor([2 / (w - 1), 0.0])
        dy = p2d.new_tensor([0.0, 2 / (h - 1)])
        grid = torch.cat([grid, grid - dx, grid + dx, grid - dy, grid + dy], 1)
    out = grid_sample(maps, grid[:, None], mode="bilinear", align_corners=True)
    if not gradients:
        return out.reshape(b, c, n).transpose(-1, -2), None
    taps = out.reshape(b, c, 5, n)  # the value, x - 1, x + 1, y - 1, y + 1
    values, plus, minus = taps[:, :, 0].transpose(-1, -2), taps[:, :, 2::2], taps[:, :, 1::2]
    if torch.is_grad_enabled():  # (B, N, 2, C) in memory: a training unroll's matmuls over C read rows
        return values, ((plus - minus) / 2).permute(0, 3, 2, 1).contiguous().transpose(-1, -2)
    # at inference (B, C, 2, N), as grid_sample writes samples: the LM sums over C along rows of points
    # (``pixloc.optim.cost.linearize``); (x + 1) - (x - 1) halved is the official (x1 - x0) / 2
    return values, (plus - minus).mul_(0.5).permute(0, 3, 1, 2)


# the 12 cells that the 5 taps of ``_bilinear`` at a point read, as offsets from its top-left cell (x0, y0):
# rows y0 and y0 + 1 at columns x0 - 1 .. x0 + 2 (the value and the taps at x +- 1), then rows y0 - 1 and
# y0 + 2 at columns x0 and x0 + 1 (the taps at y +- 1)
_TAP_CELLS_X = torch.tensor([-1, 0, 1, 2, -1, 0, 1, 2, 0, 1, 0, 1])
_TAP_CELLS_Y = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1, -1, -1, 2, 2])
# where the 20 nonzero cell weights go among the 3 x 12 (value, d/dx, d/dy) of ``_tap_weights``, in the order
# [q, -q / 2, q / 2, -q / 2, q / 2] for q the bilinear weights of the cells (x0, y0), (x0 + 1, y0),
# (x0, y0 + 1), (x0 + 1, y0 + 1)
_TAP_WEIGHT_SLOTS = torch.tensor([1, 2, 5, 6, 12, 13, 16, 17, 14, 15, 18, 19, 32, 33, 25, 26, 29, 30, 34, 35])


def _tap_weights(fx: Tensor, fy: Tensor) -> Tensor:
    """(..., 3, 12): the weights of the 12 cells (``_TAP_CELLS_X``, ``_TAP_CELLS_Y``) in the bilinear
    value and in the central differences at +- 1 px along x and y, at fractions fx, fy (...)."""
    q = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
    half = q * 0.5
    src = torch.cat([q, -half, half, -half, half], -1)
    out = q.new_zeros(*q.shape[:-1], 36).index_copy_(-1, _TAP_WEIGHT_SLOTS.to(q.device), src)
    return out.reshape(*q.shape[:-1], 3, 12)


def can_reduce_taps(maps: Tensor) -> bool:
    """Whether ``reduce_taps`` can read ``maps`` in place: on CPU, laid out channels-last (the rows of
    cells that it gathers are then views of the map), at least 2 x 2 cells."""
    return maps.device.type == "cpu" and maps.dim() == 4 and min(maps.shape[-2:]) >= 2 \
        and maps.permute(0, 2, 3, 1).is_contiguous()


def reduce_taps(maps: Tensor, p2d: Tensor, F_ref: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """The official 5-tap samples of ``_bilinear`` at p2d (B, N, 2), reduced against reference features
    F_ref (B, N, C), without forming the samples: |r|^2 (B, N), J_f^T r (B, N, 2) and J_f^T J_f
    (B, N, 2, 2) for r = F(p) - F_ref and J_f the gradients of the first C channels, and the values of
    the channels after C (B, N, K - C). For inference on CPU (``can_reduce_taps``): maps (B, K, H, W),
    K >= C, channels-last.

    The value and the taps at x +- 1 and y +- 1 read 12 cells around a point, whose channels are
    contiguous rows of a channels-last map: they are gathered as rows, and the 3 samples are one
    (3 x 12) @ (12 x K) product per point, the products over C one (3 x C) @ (C x 3). grid_sample reads
    the same cells a channel at a time, and the reductions then ran over 5 (B, C, N) samples: 1.5-1.8x
    slower for the 129-channel maps of a 1,024 px query. The same figures to float rounding (coordinates
    as ``_bilinear`` clamps them, zeros outside the map, and zeros at non-finite coordinates)."""
    b, k, h, w = maps.shape
    C = F_ref.shape[-1]
    p = torch.nan_to_num(p2d, nan=-1e9)  # far outside: zeros, as grid_sample gives non-finite points
    # the clamp of ``_bilinear``'s grid to twice the map, then to where every tap reads outside it (zeros)
    x = p[..., 0].clamp((1 - w) / 2, 3 * (w - 1) / 2).clamp(-3, w + 2)
    y = p[..., 1].clamp((1 - h) / 2, 3 * (h - 1) / 2).clamp(-3, h + 2)
    x0, y0 = x.floor(), y.floor()
    cx = x0.long()[..., None] + _TAP_CELLS_X.to(p.device)
    cy = y0.long()[..., None] + _TAP_CELLS_Y.to(p.device)
    rows = cy.clamp(0, h - 1) * w + cx.clamp(0, w - 1) + (torch.arange(b, device=p.device) * (h * w))[:, None, None]
    cells = maps.permute(0, 2, 3, 1).reshape(b * h * w, k).index_select(0, rows.reshape(-1))
    # zero padding: the cells outside the map are zeros (not the border cells their rows were clamped to,
    # which a map decoded where it is read may not hold: ``pipeline.localization.finest``)
    outside = ((cx < 0) | (cx >= w) | (cy < 0) | (cy >= h)).reshape(-1)
    cells.index_fill_(0, outside.nonzero()[:, 0], 0.0)
    samples = _tap_weights(x - x0, y - y0) @ cells.reshape(b, -1, 12, k)  # B x N x 3 (value, d/dx, d/dy) x K
    rest = samples[:, :, 0, C:].clone()
    samples[..., C:] = 0
    samples[:, :, 0, :C] -= F_ref
    gram = samples @ samples.transpose(-1, -2)  # B x N x 3 x 3: r . r, J_f^T r, J_f^T J_f
    return gram[..., 0, 0], gram[..., 1:, 0], gram[..., 1:, 1:], rest


def append_gradient_maps(maps: Tensor, channels: int,
                         memory_format: torch.memory_format = torch.contiguous_format) -> Tensor:
    """(B, K + 2 channels, H, W): ``maps`` (B, K, H, W), then the central differences of its first
    ``channels`` channels along x, then along y: (m(x + 1) - m(x - 1)) / 2, zero outside the map.

    Bilinear sampling is linear in the map and commutes with whole-pixel shifts, so sampling these
    at p gives the central differences of bilinear samples at p +- 1 px, the official gradients of
    ``_bilinear``, at every p inside the map (the zeros outside match grid_sample's zero padding),
    to rounding: 3 channel blocks sampled once instead of 5 samples per point, which pays when a
    map is sampled at many points over many iterations (``Interpolator.sample_with_gradients``).
    """
    b, k, h, w = maps.shape
    out = maps.new_zeros((b, k + 2 * channels, h, w)).contiguous(memory_format=memory_format)
    out[:, :k] = maps
    m = maps[:, :channels]
    gx, gy = out[:, k:k + channels], out[:, k + channels:]
    if w > 1:
        gx[..., 1:-1] = (m[..., 2:] - m[..., :-2]) / 2
        gx[..., 0] = m[..., 1] / 2
        gx[..., -1] = -m[..., -2] / 2
    if h > 1:
        gy[..., 1:-1, :] = (m[..., 2:, :] - m[..., :-2, :]) / 2
        gy[..., 0, :] = m[..., 1, :] / 2
        gy[..., -1, :] = -m[..., -2, :] / 2
    return out


# Keys' cubic convolution kernel (a = -0.5) as a polynomial basis, the same
# kernel as OpenCV's INTER_CUBIC; see R. Keys, IEEE TASSP 1981.
_KEYS = torch.tensor([[-1, 2, -1, 0], [3, -5, 0, 2], [-3, 4, 1, 0], [1, -1, 0, 0]]) / 2


def _bicubic(maps: Tensor, p2d: Tensor, gradients: bool) -> Tuple[Tensor, Optional[Tensor]]:
    b, c, h, w = maps.shape
    n = p2d.shape[1]
    base = _KEYS.to(p2d)
    p0 = torch.floor(p2d)
    frac = p2d - p0  # B x N x 2
    offsets = torch.arange(-1, 3, device=p2d.device)
    xs = (p0[..., 0:1].long() + offsets).clamp(0, w - 1)  # B x N x 4
    ys = (p0[..., 1:2].long() + offsets).clamp(0, h - 1)
    idx = (ys[..., :, None] * w + xs[..., None, :]).reshape(b, 1, n * 16)
    patches = maps.reshape(b, c, h * w).gather(-1, idx.expand(b, c, n * 16))
    patches = patches.reshape(b, c, n, 4, 4)  # rows = y, cols = x
    powers = torch.stack([frac ** 3, frac ** 2, frac, torch.ones_like(frac)], -1)  # B x N x 2 x 4
    coeffs = powers @ base.T  # B x N x 2 x 4: weights of the 4 taps per axis
    cx, cy = coeffs[..., 0, :], coeffs[..., 1, :]
    values = torch.einsum("bni,bnj,bcnij->bnc", cy, cx, patches)
    if not gradients:
        return values, None
    d_powers = torch.stack([3 * frac ** 2, 2 * frac, torch.ones_like(frac), torch.zeros_like(frac)], -1)
    d_coeffs = d_powers @ base.T
    dcx, dcy = d_coeffs[..., 0, :], d_coeffs[..., 1, :]
    gx = torch.einsum("bni,bnj,bcnij->bnc", cy, dcx, patches)
    gy = torch.einsum("bni,bnj,bcnij->bnc", dcy, cx, patches)
    return values, torch.stack([gx, gy], -1)


_MODES = {"linear": _bilinear, "cubic": _bicubic}


class Interpolator:
    """Samples dense maps at sub-pixel points.

    mode: ``linear`` (official PixLoc) or ``cubic`` (Keys, needs one more pixel
    of margin). pad: border margin in pixels of the map; points closer to the
    border are marked invalid (official ``interpolation.pad``). gradient_maps
    (linear mode): the LM samples precomputed central-difference maps
    (``append_gradient_maps``, the same gradients) rather than 5 taps per point at
    crowded levels (``pixloc.optim.cost.use_gradient_maps``); the LM solver turns
    them on (docs/benchmarks.md, "RGB-D maps"). cell_products (with gradient maps): at inference, the
    LM reads maps of few cells through the inner products of their cells
    (``pixloc.optim.cost.CellProducts``, the same figures) instead of sampling them.
    tap_reducer: a compiled implementation of ``reduce_taps`` (the same arguments and results, e.g.
    ``pipeline.kernels.reduce_taps``), or None. Where it is set, the LM at inference on CPU reduces the
    5 taps with it at every level of channels-last maps, in place of gradient maps and cell products
    (``pixloc.optim.cost.use_compiled_taps``).
    """

    def __init__(self, mode: str = "linear", pad: int = 2, gradient_maps: bool = False, cell_products: bool = True,
                 tap_reducer: Optional[Callable[[Tensor, Tensor, Tensor], Tuple[Tensor, ...]]] = None):
        if mode not in _MODES:
            raise ValueError(f"Unknown interpolation mode {mode!r}; known: {sorted(_MODES)}.")
        self.mode = mode
        self.pad = pad
        self.gradient_maps = gradient_maps and mode == "linear"
        self.cell_products = cell_products and self.gradient_maps
        self.tap_reducer = tap_reducer if mode == "linear" else None

    def __call__(self, maps: Tensor, p2d: Tensor, gradients: bool = False
                 ) -> Tuple[Tensor, Tensor, Optional[Tensor]]:
        """Sample ``maps`` at ``p2d``.

        maps: (B, C, H, W) or (C, H, W); p2d: (B, N, 2) or (N, 2) pixels.
        Returns values (B, N, C), validity (B, N) (inside the margin) and, if
        ``gradients``, d values / d p2d (B, N, C, 2); unbatched inputs give
        unbatched outputs.
        """
        batched = maps.dim() == 4
        if not batched:
            if maps.dim() != 3 or p2d.dim() != 2:
                raise ValueError(f"Expected maps (C, H, W) and points (N, 2), got {tuple(maps.shape)} "
                                 f"and {tuple(p2d.shape)}.")
            maps, p2d = maps[None], p2d[None]
        if p2d.dim() != 3 or p2d.shape[-1] != 2 or p2d.shape[0] != maps.shape[0]:
            raise ValueError(f"Expected maps (B, C, H, W) and points (B, N, 2), got {tuple(maps.shape)} "
                             f"and {tuple(p2d.shape)}.")
        h, w = maps.shape[-2:]
        pad = self.pad + (1 if self.mode == "cubic" else 0)
        valid = mask_in_image(p2d, p2d.new_tensor([w, h]), pad)
        values, grads = _MODES[self.mode](maps, p2d, gradients)
        if not batched:
            values, valid = values[0], valid[0]
            grads = None if grads is None else grads[0]
        return values, valid, grads

    def sample_with_gradients(self, stacked: Tensor, p2d: Tensor, channels: int) -> Tuple[Tensor, Tensor, Tensor]:
        """Linear mode, batched: sample maps and their gradient maps stacked by ``append_gradient_maps``
        (B, K + 2 channels, H, W) at p2d (B, N, 2). Returns values (B, N, K), validity (B, N) and
        the gradients of the first ``channels`` channels (B, N, channels, 2), as ``__call__`` does."""
        if self.mode != "linear":
            raise ValueError(f"Gradient maps give the gradients of linear interpolation, not {self.mode!r}.")
        b, total, h, w = stacked.shape
        k = total - 2 * channels
        valid = mask_in_image(p2d, p2d.new_tensor([w, h]), self.pad)
        grid = ((p2d / p2d.new_tensor([w - 1, h - 1])) * 2 - 1).clamp(min=-2, max=2)
        out = grid_sample(stacked, grid[:, None], mode="bilinear", align_corners=True)
        out = out.reshape(b, total, -1)  # B x (K + 2 channels) x N
        # laid out (B, 2, C, N) in memory, as grid_sample writes them: the solver sums over C along rows of
        # points (``pixloc.optim.cost.linearize``)
        grads = out[:, k:].reshape(b, 2, channels, -1).permute(0, 3, 2, 1)
        return out[:, :k].transpose(-1, -2), valid, grads
