"""The compiled kernel of the LM's taps (``pipeline.kernels``) against the torch code it replaces."""

import pytest
import torch

from pipeline import kernels
from pipeline.runtime import NO_KERNELS_ENV
from pixloc.interpolation import reduce_taps
from pixloc.optim import LevenbergMarquardt
from pixloc.optim.cost import (Linearization, build_system, linearize, use_cell_products, use_compiled_taps,
                               use_gradient_maps)

from tests.pixloc.optim.test_cells import coarse_problem

needs_numba = pytest.mark.skipif(not kernels.available(), reason="numba is not importable (or PIXLOC_NO_KERNELS)")


def _damaged_points(B, N, H, W, generator):
    """Points over the map, its border and beyond it, with NaN and infinite coordinates mixed in."""
    p = torch.rand(B, N, 2, generator=generator) * torch.tensor([W + 8.0, H + 8.0]) - 4
    k = torch.randint(0, B * N, (N // 4,), generator=generator)
    bad = torch.tensor([float("nan"), float("inf"), -float("inf"), 1e30, -1e30, 0.0, W - 1.0, H - 1.0])
    p.view(-1)[k] = bad[torch.randint(0, len(bad), (len(k),), generator=generator)]
    p[0, :3] = torch.tensor([[0.0, 0.0], [W - 1.0, H - 1.0], [W - 1.5, 0.5]])  # corners, exactly
    return p


@needs_numba
@pytest.mark.parametrize("seed", range(6))
def test_the_compiled_taps_give_the_torch_figures_at_any_point(seed):
    """At points anywhere (inside, on the border, outside, NaN, infinite), on maps of any size from
    2 x 2, with confidence channels or none: the same |r|^2, J_f^T r, J_f^T J_f and values as
    ``pixloc.interpolation.reduce_taps``, to float rounding."""
    g = torch.Generator().manual_seed(seed)
    B, C = int(torch.randint(1, 4, (1,), generator=g)), int(torch.randint(1, 70, (1,), generator=g))
    K = C + int(torch.randint(0, 3, (1,), generator=g))
    H, W = (int(x) for x in torch.randint(2, 40, (2,), generator=g))
    maps = torch.randn(B, K, H, W, generator=g).contiguous(memory_format=torch.channels_last)
    p2d = _damaged_points(B, 257, H, W, g)
    F = torch.randn(B, 257, C, generator=g)
    with torch.no_grad():
        got, want = kernels.reduce_taps(maps, p2d, F), reduce_taps(maps, p2d, F)
    for a, b, name in zip(got, want, ("|r|^2", "J_f^T r", "J_f^T J_f", "values")):
        assert a.shape == b.shape and a.dtype == b.dtype, name
        assert torch.isfinite(a).all(), name
        scale = max(1.0, float(b.abs().amax()) if b.numel() else 1.0)
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * scale, msg=name)


@needs_numba
@pytest.mark.parametrize("seed", range(3))
def test_the_compiled_normal_equations_give_the_torch_figures(seed):
    """g and H from random Jacobian factors and weights (zeros among them, as invalid points have):
    the torch figures to float rounding (the kernel sums in float64), H symmetric."""
    g = torch.Generator().manual_seed(seed)
    B, N = int(torch.randint(1, 4, (1,), generator=g)), int(torch.randint(1, 3000, (1,), generator=g))
    A = torch.randn(B, N, 2, 2, generator=g)
    lin = Linearization(None, None, None, torch.randn(B, N, 2, generator=g), A @ A.transpose(-1, -2),
                        torch.randn(B, N, 2, 6, generator=g) * 10)
    weights = torch.rand(B, N, generator=g) * (torch.rand(B, N, generator=g) > 0.3)
    with torch.no_grad():
        (g1, H1), (g0, H0) = kernels.build_system(lin, weights), build_system(lin, weights)
    torch.testing.assert_close(g1, g0, rtol=1e-4, atol=1e-4 * float(g0.abs().max()))
    torch.testing.assert_close(H1, H0, rtol=1e-4, atol=1e-4 * float(H0.abs().max()))
    assert torch.equal(H1, H1.transpose(-1, -2))


def test_anything_the_kernel_does_not_take_goes_to_the_torch_code():
    """Float64, maps not channels-last, autograd: the torch figures, with their gradients; the same for
    the normal equations."""
    maps = torch.randn(1, 5, 6, 7, dtype=torch.float64).contiguous(memory_format=torch.channels_last)
    p, F = torch.rand(1, 20, 2, dtype=torch.float64) * 5, torch.randn(1, 20, 4, dtype=torch.float64)
    with torch.no_grad():
        for a, b in zip(kernels.reduce_taps(maps, p, F), reduce_taps(maps, p, F)):
            assert torch.equal(a, b)
        for a, b in zip(kernels.reduce_taps(maps.float().contiguous(), p.float(), F.float()),
                        reduce_taps(maps.float().contiguous(), p.float(), F.float())):
            assert torch.equal(a, b)
    F32 = F.float().requires_grad_()
    kernels.reduce_taps(maps.float(), p.float(), F32)[0].sum().backward()
    assert F32.grad is not None and torch.isfinite(F32.grad).all()
    lin = Linearization(None, None, None, torch.randn(1, 9, 2), torch.eye(2).expand(1, 9, 2, 2),
                        torch.randn(1, 9, 2, 6, requires_grad=True))
    g, H = kernels.build_system(lin, torch.rand(1, 9))
    H.sum().backward()
    assert lin.J_p2d_pose.grad is not None


@needs_numba
@pytest.mark.parametrize("H, W", [(10, 16), (40, 64)])
def test_with_the_kernel_the_lm_reduces_taps_at_every_level_and_ends_at_the_same_poses(H, W):
    """With ``tap_reducer`` set, coarse levels (cell products before) and crowded ones (gradient maps)
    reduce the taps in the kernel; with ``system_builder`` too, the LM ends at the poses the torch code
    gives, to rounding."""
    problem, T0 = coarse_problem(N=1500, C=128, H=H, W=W, dtype=torch.float32, basin=True)
    torch_lm = LevenbergMarquardt(interpolation="linear", gradient_maps=True).eval()
    compiled = LevenbergMarquardt(interpolation="linear", gradient_maps=True).eval()
    compiled.interpolator.tap_reducer, compiled.system_builder = kernels.reduce_taps, kernels.build_system
    with torch.no_grad():
        assert use_gradient_maps(problem, torch_lm.interpolator)
        assert not use_compiled_taps(problem, torch_lm.interpolator)
        assert use_cell_products(problem, torch_lm.interpolator) == (H * W <= 256)
        assert use_compiled_taps(problem, compiled.interpolator)
        assert not use_gradient_maps(problem, compiled.interpolator)
        assert not use_cell_products(problem, compiled.interpolator)
        a, b = linearize(T0, problem, torch_lm.interpolator), linearize(T0, problem, compiled.interpolator)
        assert torch.equal(a.valid, b.valid) and a.valid.float().mean() > 0.2
        for name in ("sq", "Jf_r", "Jf_Jf", "confidence"):  # where valid: cell products read border cells outside
            x, y = getattr(a, name)[a.valid], getattr(b, name)[a.valid]
            torch.testing.assert_close(y, x, rtol=1e-4, atol=1e-5 * float(x.abs().max()), msg=name)
        want, got = torch_lm(problem, T0), compiled(problem, T0)
    assert torch.equal(want.failed, got.failed)
    dR, dt = (got.pose @ want.pose.inv()).magnitude()
    assert float(dt.max()) < 1e-4 and float(dR.max()) < 1e-3  # scene units, degrees
    assert float((got.pose @ T0.inv()).magnitude()[1].max()) > 1e-3  # it moved: the comparison is not vacuous
    with torch.enable_grad():  # a training unroll keeps the differentiable samplers
        assert not use_compiled_taps(problem, compiled.interpolator)


def test_pixloc_no_kernels_turns_them_off():
    """``PIXLOC_NO_KERNELS=1``: the torch code everywhere (a fresh process: the choice is made once)."""
    import os
    import subprocess
    import sys
    code = ("from pipeline import kernels; import torch; m = torch.rand(1, 3, 4, 4).contiguous(memory_format="
            "torch.channels_last); torch.set_grad_enabled(False); "
            "print(kernels.available(), kernels.reduce_taps(m, torch.rand(1, 5, 2) * 3, torch.rand(1, 5, 2))[0].shape)")
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, NO_KERNELS_ENV: "1"},
                         capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "False" and out[1] == "torch.Size([1,"
