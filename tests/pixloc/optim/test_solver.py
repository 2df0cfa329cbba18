import numpy as np
import pytest
import torch

from pixloc.geometry import Camera, Pose
from pixloc.geometry import lie
from pixloc.interpolation import Interpolator
from pixloc.optim import (ConstantDamping, FeaturemetricProblem, LearnedDamping, LevenbergMarquardt,
                          build_system, linearize)
from pixloc.optim.cost import use_gradient_maps, use_reduced_taps
from workflows.benchmarks.lm import make_problems


def load_case(oracle, k, device="cpu"):
    d = np.load(oracle / f"lm_case_{k}.npz")
    t = lambda key: torch.from_numpy(d[key]).to(device)  # noqa: E731
    W_ref = t("W_ref")[:, 0] if "W_ref" in d.files else None
    W_query = t("W_query")[0] if "W_query" in d.files else None  # stored as 1 x H x W
    problem = FeaturemetricProblem.single(t("p3d"), t("F_ref"), t("F_query"), Camera(t("camera")), W_ref, W_query)
    return d, problem, Pose(t("T_init")).reshape(1)


@pytest.mark.parametrize("k", range(5))
def test_official_lm_cases(oracle, k, device):
    d, problem, T_init = load_case(oracle, k, device)
    solver = LevenbergMarquardt(ConstantDamping(torch.from_numpy(d["damping_lambda"]).tolist()),
                                num_iters=int(d["num_iters"]), pad=2).eval()
    result = solver(problem, T_init, record_trajectory=True)
    traj = result.trajectory.data[0].cpu().numpy()
    assert traj.shape == d["trajectory"].shape  # same number of iterations
    np.testing.assert_allclose(traj, d["trajectory"], atol=1e-4, rtol=0)
    np.testing.assert_allclose(result.pose.data[0].cpu().numpy(), d["T_out"], atol=1e-4, rtol=0)
    assert bool(result.failed[0]) == bool(d["failed"])
    assert result.num_iters == len(d["trajectory"])


def test_jacobian_of_residuals_matches_autograd():
    problem, T = make_problems(2, 30, 8, "cpu")
    problem = FeaturemetricProblem(problem.p3d_world.double(), problem.F_ref.double(),
                                   problem.F_query.double(), problem.camera.double())
    T = T.double()
    interp = Interpolator("cubic", pad=2)  # analytic gradients: exact Jacobian
    lin = linearize(T, problem, interp)
    J = lin.J_f @ lin.J_p2d_pose  # B x N x C x 6

    def residuals(delta):
        dT = Pose.from_Rt(lie.so3_exp(delta[..., 3:]), delta[..., :3])
        return linearize(dT @ T, problem, interp).res

    delta = torch.zeros(2, 6, dtype=torch.float64)
    J_auto = torch.autograd.functional.jacobian(residuals, delta)  # B x N x C x B x 6
    J_auto = torch.stack([J_auto[b, :, :, b] for b in range(2)])
    torch.testing.assert_close(J, J_auto)
    # The factored normal equations equal the naive ones.
    w = torch.rand(2, 30, dtype=torch.float64)
    g, H = build_system(lin, w)
    torch.testing.assert_close(g, torch.einsum("bn,bncj,bnc->bj", w, J, lin.res))
    torch.testing.assert_close(H, torch.einsum("bn,bnci,bncj->bij", w, J, J))


def test_converges_from_a_perturbed_pose(device):
    problem, T_init = make_problems(4, 500, 32, device, seed=3)
    solver = LevenbergMarquardt(ConstantDamping(1e-3), num_iters=50).eval()
    result = solver(problem, T_init)
    dR0, dt0 = T_init.magnitude()
    dR, dt = result.pose.magnitude()  # the true pose is the identity
    assert not result.failed.any()
    assert (dt < 0.1 * dt0).all() and (dR < 0.1 * dR0).all(), (dt0, dt, dR0, dR)
    assert (result.cost[:, -1] < result.cost[:, 0]).all()


def test_batched_equals_one_at_a_time(device):
    problem, T_init = make_problems(5, 300, 16, device, seed=1)
    solver = LevenbergMarquardt(ConstantDamping(1e-2), num_iters=30).eval()
    batched = solver(problem, T_init)
    for i in range(5):
        single = solver(problem.index(i), T_init[[i]])
        torch.testing.assert_close(batched.pose.data[i], single.pose.data[0], atol=1e-5, rtol=0)
        assert int(batched.iterations[i]) == int(single.iterations[0])


def test_too_few_points_fail_and_keep_the_pose():
    problem, T_init = make_problems(2, 50, 8, "cpu")
    mask = torch.ones(2, 50, dtype=torch.bool)
    mask[1, 9:] = False  # 9 points left
    problem = FeaturemetricProblem(problem.p3d_world, problem.F_ref, problem.F_query, problem.camera, mask=mask)
    result = LevenbergMarquardt(num_iters=5).eval()(problem, T_init)
    assert result.failed.tolist() == [False, True]
    torch.testing.assert_close(result.pose.data[1], T_init.data[1])


def test_nan_never_comes_out_as_success():
    problem, T_init = make_problems(2, 100, 8, "cpu")
    F_query = problem.F_query.clone()
    F_query[1] = float("nan")
    problem = FeaturemetricProblem(problem.p3d_world, problem.F_ref, F_query, problem.camera)
    result = LevenbergMarquardt(num_iters=5).eval()(problem, T_init)
    assert result.failed.tolist() == [False, True]
    assert result.pose.isfinite().all()


def test_bad_input_is_named():
    problem, T_init = make_problems(2, 20, 8, "cpu")
    solver = LevenbergMarquardt(num_iters=2)
    bad = Pose(T_init.data.clone())
    bad.data[0, 9] = float("nan")
    with pytest.raises(ValueError, match="T_init contains NaN"):
        solver(problem, bad)
    with pytest.raises(ValueError, match=r"batch shape \(2,\)"):
        solver(problem, T_init[[0]])
    p3d = problem.p3d_world.clone()
    p3d[0, 3, 1] = float("nan")
    with pytest.raises(ValueError, match="p3d_world contains NaN"):
        FeaturemetricProblem(p3d, problem.F_ref, problem.F_query, problem.camera)
    with pytest.raises(ValueError, match=r"F_ref must be \(B, N, C\)"):
        FeaturemetricProblem(problem.p3d_world, problem.F_ref[:, :5], problem.F_query, problem.camera)
    with pytest.raises(ValueError, match="both W_ref and W_query"):
        FeaturemetricProblem(problem.p3d_world, problem.F_ref, problem.F_query, problem.camera,
                             W_ref=torch.ones(2, 20))


def test_unrolled_solver_is_differentiable():
    """Gradients of the refined pose reach features, confidences and the learned damping."""
    problem, T_init = make_problems(1, 40, 4, "cpu", seed=2)
    leaves = {k: getattr(problem, k).double().requires_grad_(True)
              for k in ("F_ref", "F_query", "W_ref", "W_query")}
    damping = LearnedDamping().double()
    solver = LevenbergMarquardt(damping, num_iters=3).double().train()

    def refined(F_ref, F_query, W_ref, W_query):
        p = FeaturemetricProblem(problem.p3d_world.double(), F_ref, F_query, problem.camera.double(),
                                 W_ref, W_query)
        return solver(p, T_init.double()).pose.data

    out = refined(**leaves)
    grads = torch.autograd.grad(out.sum(), list(leaves.values()) + [damping.theta])
    for g in grads:
        assert torch.isfinite(g).all() and g.abs().sum() > 0
    # Analytic-vs-numeric check of the whole unroll w.r.t. the reference features.
    torch.autograd.gradcheck(lambda F: refined(F, *[leaves[k].detach() for k in ("F_query", "W_ref", "W_query")]),
                             (leaves["F_ref"].detach().requires_grad_(True),), atol=1e-5, rtol=1e-3)


def test_chunked_linearization_equals_whole_batch():
    problem, T_init = make_problems(5, 200, 16, "cpu", seed=4)
    whole = LevenbergMarquardt(ConstantDamping(1e-2), num_iters=12).eval()(problem, T_init)
    chunked = LevenbergMarquardt(ConstantDamping(1e-2), num_iters=12, chunk_points=400).eval()
    assert len(chunked._chunks(problem)) == 3  # 2 + 2 + 1 problems
    result = chunked(problem, T_init)
    torch.testing.assert_close(result.pose.data, whole.pose.data, atol=1e-6, rtol=0)
    torch.testing.assert_close(result.cost, whole.cost)
    assert result.iterations.tolist() == whole.iterations.tolist()


def test_gradient_maps_give_the_official_linearization():
    """Where points outnumber half the cells, the LM samples precomputed gradient maps: the same
    residuals and Jacobians as the 5 official taps, hence the same solve."""
    problem, T_init = make_problems(2, 12000, 16, "cpu", seed=5)  # 120 x 160 maps: 19,200 cells
    double = FeaturemetricProblem(problem.p3d_world.double(), problem.F_ref.double(),
                                  problem.F_query.double(), problem.camera.double())
    maps, taps = Interpolator("linear", pad=2, gradient_maps=True), Interpolator("linear", pad=2)
    assert use_gradient_maps(double, maps) and not use_gradient_maps(double, taps)
    few = FeaturemetricProblem(double.p3d_world[:, :100], double.F_ref[:, :100], double.F_query, double.camera)
    assert not use_gradient_maps(few, maps)  # fine levels with few points keep the taps
    a, b = linearize(T_init.double(), double, maps), linearize(T_init.double(), double, taps)
    assert torch.equal(a.valid, b.valid)
    torch.testing.assert_close(a.res, b.res, rtol=0, atol=1e-12)
    torch.testing.assert_close(a.J_f, b.J_f, rtol=0, atol=1e-12)
    solve = {}
    for name, interp in (("maps", maps), ("taps", taps)):
        solver = LevenbergMarquardt(ConstantDamping(1e-2), num_iters=20).eval()
        solver.interpolator = interp
        solve[name] = solver(problem, T_init)
    torch.testing.assert_close(solve["maps"].pose.data, solve["taps"].pose.data, atol=1e-5, rtol=0)


def test_problems_that_stopped_are_no_longer_linearized(monkeypatch):
    """A batch where some problems converge early: from the check where they stop, only the others are
    linearized (their points are the only work left), and every result equals its one-at-a-time solve."""
    import pixloc.optim.solver as solver_module
    problem, T_init = make_problems(4, 300, 16, "cpu", seed=1)
    T_init = Pose(torch.stack([Pose.from_Rt(torch.eye(3), torch.zeros(3)).data, *T_init.data[1:]]))  # 0 starts at truth
    solver = LevenbergMarquardt(ConstantDamping(1e-2), num_iters=30).eval()
    sizes = []
    real = solver_module.linearize
    monkeypatch.setattr(solver_module, "linearize", lambda T, p, interp: sizes.append(len(T)) or real(T, p, interp))
    batched = solver(problem, T_init)
    iterations = batched.iterations.tolist()
    assert iterations == [1, 11, 11, 11]  # 0 stops at the first check (iteration 1), the others at the second
    assert sizes == [4] + [3] * 10  # after the first check, 3 problems linearized, not 4
    monkeypatch.setattr(solver_module, "linearize", real)
    for i in range(4):
        single = solver(problem.index(i), T_init[[i]])
        torch.testing.assert_close(batched.pose.data[i], single.pose.data[0], atol=1e-5, rtol=0)
        assert int(batched.iterations[i]) == int(single.iterations[0])
        assert float(batched.cost[i, iterations[i] - 1]) == pytest.approx(float(single.cost[0, -1]), rel=1e-5)


@pytest.mark.parametrize("sampler", ["taps", "gradient maps", "reduced taps"])
def test_inference_sums_over_channels_give_the_training_linearization(sampler):
    """At inference the products over the channels are sums along the samples' rows of points (their
    layout as grid_sample writes them), or, on channels-last maps, reduced from the taps' cells without
    the samples (``reduce_taps``); a training unroll keeps the batched matmuls: the same figures."""
    problem, T = make_problems(2, 12000, 16, "cpu", seed=6)  # 120 x 160 maps: gradient maps where allowed
    conf = torch.rand(2, 12000, dtype=torch.float64), torch.rand(2, *problem.F_query.shape[-2:], dtype=torch.float64)
    F_query = problem.F_query.double()
    if sampler == "reduced taps":
        F_query = F_query.contiguous(memory_format=torch.channels_last)
    double = FeaturemetricProblem(problem.p3d_world.double(), problem.F_ref.double(), F_query,
                                  problem.camera.double(), *conf)
    interp = Interpolator("linear", pad=2, gradient_maps=sampler == "gradient maps")
    assert use_gradient_maps(double, interp) == (sampler == "gradient maps")
    trained = linearize(T.double(), double, interp)
    with torch.no_grad():
        assert use_reduced_taps(double, interp) == (sampler == "reduced taps")
        inferred = linearize(T.double(), double, interp)
    assert torch.equal(trained.valid, inferred.valid) and trained.valid.float().mean() > 0.5
    keys = ("sq", "Jf_r", "Jf_Jf", "confidence") + (() if sampler == "reduced taps" else ("res", "J_f"))
    for key in keys:
        torch.testing.assert_close(getattr(inferred, key), getattr(trained, key), rtol=0, atol=1e-12, msg=key)
    if sampler == "reduced taps":
        assert inferred.res is None and inferred.J_f is None
    else:
        assert inferred.J_f.stride(1) == 1  # channels first: rows of points contiguous
