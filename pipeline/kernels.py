"""Compiled CPU kernels for the LM's inner loop at inference (numba): the taps and the normal equations.

``reduce_taps`` computes what ``pixloc.interpolation.reduce_taps`` does, the official 5-tap bilinear
samples of channels-last query maps reduced against the reference features, in one pass per point:
the 12 cells it reads are walked once, channel by channel, and nothing is written but the reductions.
The torch version gathers those cells into a (B, N, 12, K) tensor and multiplies small matrices per
point, and the samplers of gradient maps and cell products it replaced at crowded and coarse levels
each ran a dozen tensor ops per iteration: the LM's linearization was most of a query's CPU time
(docs/benchmarks.md, "The LM's taps and normal equations in one compiled pass per point"). The same
figures to float rounding (sums reassociated); the torch version stays the reference and the fallback.

``build_system`` forms the LM's normal equations from the per-point factors in one pass per point too.

``pixloc`` stays pure torch: the kernels are handed to its solvers (``LevenbergMarquardt.system_builder``)
and their interpolators (``Interpolator.tap_reducer``) by the localizer (``pipeline.localization.refine``).
"""

import functools
import logging
from typing import Callable, Optional, Tuple

import torch
from torch import Tensor

from pipeline.runtime import NO_KERNELS_ENV as DISABLE_ENV, kernels_disabled  # noqa: F401 (named here before)
from pixloc.interpolation import can_reduce_taps, reduce_taps as torch_reduce_taps
from pixloc.optim.cost import Linearization, build_system as torch_build_system

logger = logging.getLogger(__name__)



@functools.lru_cache(maxsize=1)
def _kernels() -> Optional[Tuple[Callable, Callable]]:
    """The compiled kernels, ``reduce_taps``' and ``build_system``'s (their machine code is cached on disk
    by numba after the first process), or None where numba is missing or turned off."""
    if kernels_disabled():
        return None
    try:
        import numba
        import numpy as np
    except ImportError as e:  # a dependency, but the torch code is complete without it
        logger.warning("numba is not importable (%s): the LM runs its torch code (slower on CPU)", e)
        return None

    # reassociation (vector sums) and contraction (FMA), but NaN and infinities kept: a NaN point is sampled
    # as far outside the map, as grid_sample does
    @numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
    def reduce(maps, p2d, F_ref, sq, Jf_r, Jf_Jf, rest):  # pragma: no cover (compiled)
        B, H, W, K = maps.shape
        N = p2d.shape[1]
        C = F_ref.shape[2]
        zero = np.zeros(K, maps.dtype)
        one, half = np.float32(1.0), np.float32(0.5)
        # ``_bilinear``'s clamp of the grid to twice the map, then to where every tap reads outside it
        lo_x, hi_x = max(np.float32((1 - W) / 2), np.float32(-3)), min(np.float32(3 * (W - 1) / 2), np.float32(W + 2))
        lo_y, hi_y = max(np.float32((1 - H) / 2), np.float32(-3)), min(np.float32(3 * (H - 1) / 2), np.float32(H + 2))
        for b in range(B):
            m = maps[b]
            for n in range(N):
                x, y = p2d[b, n, 0], p2d[b, n, 1]
                x = np.float32(-1e9) if np.isnan(x) else x
                y = np.float32(-1e9) if np.isnan(y) else y
                x, y = min(max(x, lo_x), hi_x), min(max(y, lo_y), hi_y)
                x0, y0 = np.floor(x), np.floor(y)
                fx, fy = x - x0, y - y0
                i, j = int(x0), int(y0)
                q0, q1, q2, q3 = (one - fx) * (one - fy), fx * (one - fy), (one - fx) * fy, fx * fy
                h0, h1, h2, h3 = q0 * half, q1 * half, q2 * half, q3 * half
                # the 12 cells (``pixloc.interpolation._TAP_CELLS_X``, ``_Y``), zeros outside the map:
                # rows j and j + 1 at columns i - 1 .. i + 2, then rows j - 1 and j + 2 at columns i and i + 1
                xs0, xs1, xs2, xs3 = 0 <= i - 1 < W, 0 <= i < W, 0 <= i + 1 < W, 0 <= i + 2 < W
                ys0, ys1, ys2, ys3 = 0 <= j - 1 < H, 0 <= j < H, 0 <= j + 1 < H, 0 <= j + 2 < H
                c0 = m[j, i - 1] if ys1 and xs0 else zero
                c1 = m[j, i] if ys1 and xs1 else zero
                c2 = m[j, i + 1] if ys1 and xs2 else zero
                c3 = m[j, i + 2] if ys1 and xs3 else zero
                c4 = m[j + 1, i - 1] if ys2 and xs0 else zero
                c5 = m[j + 1, i] if ys2 and xs1 else zero
                c6 = m[j + 1, i + 1] if ys2 and xs2 else zero
                c7 = m[j + 1, i + 2] if ys2 and xs3 else zero
                c8 = m[j - 1, i] if ys0 and xs1 else zero
                c9 = m[j - 1, i + 1] if ys0 and xs2 else zero
                c10 = m[j + 2, i] if ys3 and xs1 else zero
                c11 = m[j + 2, i + 1] if ys3 and xs2 else zero
                f = F_ref[b, n]
                s = r0 = r1 = a00 = a01 = a11 = np.float32(0.0)
                for k in range(C):
                    m1, m2, m5, m6 = c1[k], c2[k], c5[k], c6[k]
                    r = q0 * m1 + q1 * m2 + q2 * m5 + q3 * m6 - f[k]
                    gx = h0 * (m2 - c0[k]) + h1 * (c3[k] - m1) + h2 * (m6 - c4[k]) + h3 * (c7[k] - m5)
                    gy = h0 * (m5 - c8[k]) + h1 * (m6 - c9[k]) + h2 * (c10[k] - m1) + h3 * (c11[k] - m2)
                    s += r * r
                    r0 += gx * r
                    r1 += gy * r
                    a00 += gx * gx
                    a01 += gx * gy
                    a11 += gy * gy
                sq[b, n] = s
                Jf_r[b, n, 0], Jf_r[b, n, 1] = r0, r1
                Jf_Jf[b, n, 0, 0], Jf_Jf[b, n, 0, 1], Jf_Jf[b, n, 1, 0], Jf_Jf[b, n, 1, 1] = a00, a01, a01, a11
                for k in range(C, K):
                    rest[b, n, k - C] = q0 * c1[k] + q1 * c2[k] + q2 * c5[k] + q3 * c6[k]

    @numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
    def system(J, weights, Jf_r, Jf_Jf, g, H):  # pragma: no cover (compiled)
        B, N = weights.shape
        for b in range(B):
            acc_g = np.zeros(6)
            acc_H = np.zeros((6, 6))
            for n in range(N):
                w = np.float64(weights[b, n])
                r0, r1 = w * Jf_r[b, n, 0], w * Jf_r[b, n, 1]
                A = Jf_Jf[b, n]
                a00, a01, a10, a11 = w * A[0, 0], w * A[0, 1], w * A[1, 0], w * A[1, 1]
                for i in range(6):
                    j0, j1 = J[b, n, 0, i], J[b, n, 1, i]
                    acc_g[i] += j0 * r0 + j1 * r1
                    u0, u1 = j0 * a00 + j1 * a10, j0 * a01 + j1 * a11  # row i of J^T (w J_f^T J_f)
                    for k in range(i, 6):
                        acc_H[i, k] += u0 * J[b, n, 0, k] + u1 * J[b, n, 1, k]
            for i in range(6):
                g[b, i] = acc_g[i]
                for k in range(i, 6):
                    H[b, i, k] = H[b, k, i] = acc_H[i, k]

    return reduce, system


def available() -> bool:
    """Whether the compiled kernels are on (numba importable and not turned off by ``PIXLOC_NO_KERNELS``)."""
    return _kernels() is not None


def _compiled(*tensors: Tensor) -> Optional[Tuple[Callable, Callable]]:
    """The kernels, where they are on and take ``tensors``: float32 on CPU, without autograd; else None."""
    kernels = _kernels()
    if kernels is None or torch.is_grad_enabled() \
            or not all(t.dtype == torch.float32 and t.device.type == "cpu" for t in tensors):
        return None
    return kernels


def reduce_taps(maps: Tensor, p2d: Tensor, F_ref: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """``pixloc.interpolation.reduce_taps``, compiled: the same arguments and results. Float32 maps,
    points and features on CPU, maps channels-last (``can_reduce_taps``), no autograd; anything else
    goes to the torch version."""
    kernels = _compiled(maps, p2d, F_ref)
    if kernels is None or not can_reduce_taps(maps):
        return torch_reduce_taps(maps, p2d, F_ref)
    B, K, H, W = maps.shape
    N, C = p2d.shape[1], F_ref.shape[-1]
    sq, Jf_r = maps.new_empty((B, N)), maps.new_empty((B, N, 2))
    Jf_Jf, rest = maps.new_empty((B, N, 2, 2)), maps.new_empty((B, N, K - C))
    kernels[0](maps.permute(0, 2, 3, 1).numpy(), p2d.contiguous().numpy(), F_ref.contiguous().numpy(),
           sq.numpy(), Jf_r.numpy(), Jf_Jf.numpy(), rest.numpy())
    return sq, Jf_r, Jf_Jf, rest


def build_system(lin: Linearization, weights: Tensor) -> Tuple[Tensor, Tensor]:
    """``pixloc.optim.cost.build_system``, compiled: g (B, 6) and H (B, 6, 6) from the Jacobian factors
    of ``lin`` and the points' ``weights`` (B, N), in one pass per point, summed in float64 (the torch
    version's products of tiny matrices and passes over (B, 2 N, 6) tensors cost an LM iteration at the
    coarse levels as much as the taps did). Float32 on CPU without autograd; else the torch version."""
    parts = (lin.J_p2d_pose, weights, lin.Jf_r, lin.Jf_Jf)
    kernels = _compiled(*parts)
    if kernels is None:
        return torch_build_system(lin, weights)
    B = weights.shape[0]
    g, H = weights.new_empty((B, 6)), weights.new_empty((B, 6, 6))
    kernels[1](*(t.contiguous().numpy() for t in parts), g.numpy(), H.numpy())
    return g, H
