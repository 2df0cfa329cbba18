"""Cell products: the LM's linearization on small maps from inner products of their cells, which
must give what sampling the maps gives (``pixloc.optim.cost.CellProducts``)."""

import torch

from pixloc.geometry import Camera, Pose
from pixloc.interpolation import Interpolator
from pixloc.optim import ConstantDamping, FeaturemetricProblem, LevenbergMarquardt, linearize
from pixloc.optim.cost import CELL_PRODUCTS_MAX_BYTES, CELL_PRODUCTS_MAX_CELLS, use_cell_products
from pixloc.optim.evidence import alignment_uncertainty


def coarse_problem(B=2, N=600, C=32, H=11, W=16, seed=0, dtype=torch.float64, basin=False):
    """A coarsest level: maps of H x W cells (a 256 px query at stride 16), many more points than
    cells, some of them outside the map or behind the camera. ``basin``: reference features sampled
    where the points project at the identity pose, so that the LM converges there, the first problem
    starting at it."""
    g = torch.Generator().manual_seed(seed)
    cam = Camera(torch.tensor([W, H, 0.9 * W, 0.9 * W, (W - 1) / 2, (H - 1) / 2])).reshape(1).expand(B)
    maps = torch.nn.functional.interpolate(torch.randn(B, C, 4, 5, generator=g), size=(H, W), mode="bilinear")
    F_query = torch.nn.functional.normalize(maps, dim=1).contiguous(memory_format=torch.channels_last)
    p2d = torch.rand(B, N, 2, generator=g) * torch.tensor([W + 2.0, H + 2.0]) - 1  # some outside the map
    depth = 2 + 3 * torch.rand(B, N, 1, generator=g)
    depth[:, :10] *= -1  # behind the camera
    p3d = torch.cat([(p2d - cam.c[:, None]) / cam.f[:, None], torch.ones_like(depth)], -1) * depth
    F_ref = torch.nn.functional.normalize(torch.randn(B, N, C, generator=g), dim=-1)
    if basin:
        grid = (p2d / torch.tensor([W - 1.0, H - 1.0]) * 2 - 1)[:, None]
        F_ref = torch.nn.functional.grid_sample(F_query, grid, align_corners=True)[:, :, 0].transpose(1, 2)
    problem = FeaturemetricProblem(p3d.to(dtype), F_ref.to(dtype), F_query.to(dtype), cam.to(dtype),
                                   torch.rand(B, N, generator=g).to(dtype), torch.rand(B, H, W, generator=g).to(dtype))
    xi = torch.randn(B, 6, generator=g) * torch.tensor([0.05] * 3 + [0.02] * 3)
    if basin:
        xi[0] = 0
    return problem, Pose.exp(xi).to(dtype)


def test_cell_products_give_the_sampled_linearization():
    problem, T = coarse_problem()
    interp = Interpolator("linear", pad=2, gradient_maps=True)
    with torch.no_grad():
        assert use_cell_products(problem, interp)
        cells = linearize(T, problem, interp)
    sampled = linearize(T, problem, interp)  # gradients on (a training unroll): the maps are sampled
    assert cells.res is None and sampled.res is not None
    assert torch.equal(cells.valid, sampled.valid)
    assert 0.2 < cells.valid.double().mean() < 0.8  # points inside and outside the map, behind the camera
    for name in ("sq", "Jf_r", "Jf_Jf", "confidence"):
        a, b = getattr(cells, name), getattr(sampled, name)
        assert torch.isfinite(a).all(), name  # points outside the map too: weighted by 0, never NaN
        torch.testing.assert_close(a[cells.valid], b[cells.valid], rtol=0, atol=1e-12)


def test_cell_products_give_the_same_solve_and_uncertainty():
    problem, T = coarse_problem(dtype=torch.float32, seed=1)
    solver = LevenbergMarquardt(ConstantDamping(1e-2), num_iters=40).eval()
    sampled = solver(problem, T)
    sigma = alignment_uncertainty(problem, sampled.pose, solver.loss_fn, solver.interpolator)
    fresh, _ = coarse_problem(dtype=torch.float32, seed=1)  # its products are built once per problem
    with torch.no_grad():
        cells = solver(fresh, T)
        sigma_cells = alignment_uncertainty(fresh, sampled.pose, solver.loss_fn, solver.interpolator)
    assert "cell_products" in fresh.__dict__ and "cell_products" not in problem.__dict__
    assert cells.iterations.tolist() == sampled.iterations.tolist()
    torch.testing.assert_close(cells.pose.data, sampled.pose.data, atol=1e-5, rtol=0)
    for key in sigma:
        torch.testing.assert_close(sigma_cells[key], sigma[key], rtol=1e-4, atol=1e-6)


def test_larger_maps_and_crowds_of_points_are_sampled():
    problem, _ = coarse_problem(N=4000, H=24, W=32)  # 768 cells
    assert 24 * 32 > CELL_PRODUCTS_MAX_CELLS
    interp = Interpolator("linear", pad=2, gradient_maps=True)
    with torch.no_grad():
        assert not use_cell_products(problem, interp)
        assert not use_cell_products(coarse_problem()[0], Interpolator("linear", pad=2))  # no gradient maps
        crowd = coarse_problem(B=1, N=CELL_PRODUCTS_MAX_BYTES // (11 * 16 * 12) + 1)[0]
        assert not use_cell_products(crowd, interp)  # its products would outweigh the sampling's memory
        assert use_cell_products(coarse_problem(B=1, N=CELL_PRODUCTS_MAX_BYTES // (11 * 16 * 12))[0], interp)


def test_chunks_and_stopped_problems_share_the_batchs_products(monkeypatch):
    """The LM cuts a batch into chunks, and again as problems stop: their sub-problems read the
    products built once for the whole batch, with the same result as one chunk."""
    from pixloc.optim import cost
    built = []
    real = cost.CellProducts.of.__func__
    monkeypatch.setattr(cost.CellProducts, "of", classmethod(lambda cls, p: built.append(p.batch_size) or real(cls, p)))
    problem, T = coarse_problem(B=5, N=300, dtype=torch.float32, seed=2, basin=True)
    with torch.no_grad():
        whole = LevenbergMarquardt(ConstantDamping(1e-2), num_iters=40).eval()(problem, T)
        fresh, _ = coarse_problem(B=5, N=300, dtype=torch.float32, seed=2, basin=True)
        chunked = LevenbergMarquardt(ConstantDamping(1e-2), num_iters=40, chunk_points=600).eval()
        assert len(chunked._chunks(fresh)) == 3
        result = chunked(fresh, T)
    assert built == [5, 5]  # once per batch, not per chunk or per check where problems stop
    assert len(set(whole.iterations.tolist())) > 1  # problems stopped at different checks
    torch.testing.assert_close(result.pose.data, whole.pose.data, atol=1e-6, rtol=0)
    assert result.iterations.tolist() == whole.iterations.tolist()
