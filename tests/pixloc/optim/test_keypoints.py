"""The PnP inliers' reprojection term of the LM (``pixloc.optim.keypoints``): its Jacobian, and what it
does to the optimum of a featuremetric problem whose features and keypoints disagree."""

import torch

from pixloc.geometry import Pose, lie
from pixloc.optim import ConstantDamping, FeaturemetricProblem, LevenbergMarquardt
from pixloc.optim.keypoints import KeypointTerm
from workflows.benchmarks.lm import make_problems


def keypoints_at(problem: FeaturemetricProblem, T: Pose, m: int, weight: float, noise: float = 0.3, seed: int = 0
                 ) -> KeypointTerm:
    """m of the problem's points seen at pose T, with ``noise`` px of Gaussian noise, as PnP inliers."""
    g = torch.Generator().manual_seed(seed)
    p3d = problem.p3d_world[:, :m]
    p2d = problem.camera.cam2image(T.transform(p3d))[0]
    p2d = p2d + noise * torch.randn(p2d.shape, generator=g, dtype=p2d.dtype)
    B = p3d.shape[0]
    return KeypointTerm(p3d, p2d, problem.camera, torch.full((B,), noise, dtype=p3d.dtype),
                        torch.ones(B, m, dtype=torch.bool), torch.full((B,), weight, dtype=p3d.dtype))


def test_the_residuals_jacobian_matches_autograd():
    problem, T = make_problems(2, 40, 8, "cpu", seed=2)
    problem = FeaturemetricProblem(problem.p3d_world.double(), problem.F_ref.double(), problem.F_query.double(),
                                   problem.camera.double())
    T = T.double()
    term = keypoints_at(problem, Pose.identity(2).double(), 30, 1.0)
    _, J, valid = term.residuals(T)

    def residuals(delta):
        return term.residuals(Pose.from_Rt(lie.so3_exp(delta[..., 3:]), delta[..., :3]) @ T)[0]

    J_auto = torch.autograd.functional.jacobian(residuals, torch.zeros(2, 6, dtype=torch.float64))
    J_auto = torch.stack([J_auto[b, :, :, b] for b in range(2)])
    assert bool(valid.all())
    torch.testing.assert_close(J, J_auto)


def test_the_keypoints_hold_the_pose_in_proportion_to_their_weight():
    """Features whose optimum is the identity, keypoints seen from a pose 2 cm and 0.3 deg away: at weight
    0 the LM ends at the features' optimum; with the term, at a pose that fits the keypoints better than
    the features' optimum does and the features better than the keypoints' pose does, nearer the
    keypoints as their weight grows."""
    problem, T_init = make_problems(3, 400, 16, "cpu", seed=5)
    g = torch.Generator().manual_seed(1)
    noisy = problem.F_ref + 0.02 * torch.randn(problem.F_ref.shape, generator=g)
    problem = FeaturemetricProblem(problem.p3d_world, noisy, problem.F_query, problem.camera, problem.W_ref,
                                   problem.W_query)
    T_k = Pose.exp(torch.tensor([0.02, -0.01, 0.01, 0.003, 0.004, -0.002]).expand(3, 6))
    solver = LevenbergMarquardt(ConstantDamping(1e-3), num_iters=100).eval()
    plain = solver(problem, T_init).pose
    none = solver(problem, T_init, keypoints=keypoints_at(problem, T_k, 60, 0.0)).pose
    torch.testing.assert_close(none.data, plain.data)
    term = keypoints_at(problem, T_k, 60, 1.0)
    joint, firm = (solver(problem, T_init, keypoints=keypoints_at(problem, T_k, 60, w)).pose for w in (1.0, 100.0))

    def features(T):  # the mean robust featuremetric cost at T
        return solver(problem, T, num_iters=1).cost[:, 0]

    assert bool((term.chi2(joint) < term.chi2(plain)).all() and (term.chi2(firm) < term.chi2(joint)).all())
    assert bool((features(joint) < features(T_k)).all() and (features(plain) < features(joint)).all())
    assert bool((term.chi2(firm) < 2 * term.chi2(T_k)).all()), (term.chi2(firm), term.chi2(T_k))
