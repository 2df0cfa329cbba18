"""Problems solved as bodies (``pixloc.optim.bodies``): the adjoint's chain rule, a body of one camera
that is the plain solve, and a rig whose cameras pin down together what each alone does not."""

import math

import torch

from pixloc.geometry import Pose, lie
from pixloc.optim import Bodies, ConstantDamping, FeaturemetricProblem, LevenbergMarquardt
from workflows.benchmarks.lm import make_problems


def rig(n: int, dtype=torch.float32) -> Pose:
    """cam_from_rig of n cameras turned 360 / n degrees apart about the rig's y axis, 0.3 m off its centre."""
    poses = []
    for i in range(n):
        a = 2 * math.pi * i / n
        R = lie.so3_exp(torch.tensor([0.0, a, 0.0], dtype=torch.float64))
        poses.append(Pose.from_Rt(R, torch.tensor([0.1, 0.0, -0.3], dtype=torch.float64)))
    return Pose.stack(poses).to(dtype)


def test_the_adjoint_moves_each_camera_as_the_body_moves():
    """The Jacobian of points seen by a camera of the body w.r.t. a left update of the body equals the
    camera's own Jacobian times its adjoint."""
    C = rig(3, torch.float64)
    T_body = Pose.exp(torch.tensor([0.3, -0.2, 1.0, 0.1, 0.4, -0.2], dtype=torch.float64)).reshape(1)
    bodies = Bodies(torch.zeros(3, dtype=torch.long), C)
    p = torch.randn(3, 5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def points(delta):  # the points in each camera after the body's update delta = (t, w)
        return (C @ (Pose.from_Rt(lie.so3_exp(delta[3:]), delta[:3]) @ T_body)[bodies.index]).transform(p)

    J_auto = torch.autograd.functional.jacobian(points, torch.zeros(6, dtype=torch.float64))
    p_cam = bodies.camera_poses(T_body).transform(p)
    J_chain = Pose.identity(1).J_transform(p_cam) @ bodies.adjoint[:, None]
    torch.testing.assert_close(J_chain, J_auto)


def test_a_body_of_one_camera_is_the_plain_solve():
    problem, T_init = make_problems(4, 200, 8, "cpu", seed=3)
    solver = LevenbergMarquardt(ConstantDamping(1e-3), num_iters=60).eval()
    plain = solver(problem, T_init)
    alone = solver(problem, T_init, bodies=Bodies(torch.arange(4), Pose.identity(4)))
    torch.testing.assert_close(alone.pose.data, plain.pose.data, atol=1e-6, rtol=0)
    assert torch.equal(alone.iterations, plain.iterations)
    torch.testing.assert_close(alone.body_pose.data, alone.pose.data)


def rig_problem(n: int, points: int, seed: int):
    """n cameras of one rig at the identity body pose, each with its own map and points (in the world):
    the problems of ``make_problems`` moved so that camera b's ground truth is cam_from_rig[b]."""
    problem, _ = make_problems(n, points, 16, "cpu", seed=seed)
    C = rig(n)
    p3d_world = torch.stack([C[b].inv().transform(problem.p3d_world[b]) for b in range(n)])
    return FeaturemetricProblem(p3d_world, problem.F_ref, problem.F_query, problem.camera, problem.W_ref,
                                problem.W_query), C


def test_a_rig_converges_as_one_body_where_a_camera_alone_cannot():
    """Three cameras of a rig from a start 3 cm and 1 deg off: one camera has 6 points (fewer than the 10 a
    problem needs: alone it fails); as one body the three reach the true rig pose, and every camera's pose
    is its cam_from_rig at the body's pose."""
    problem, C = rig_problem(3, 120, seed=7)
    mask = torch.ones(3, 120, dtype=torch.bool)
    mask[2, 6:] = False
    problem = FeaturemetricProblem(problem.p3d_world, problem.F_ref, problem.F_query, problem.camera,
                                   problem.W_ref, problem.W_query, mask)
    start = Pose.exp(torch.tensor([0.03, -0.02, 0.02, 0.01, -0.012, 0.008])).reshape(1)
    T_init = C @ start.expand(3)
    solver = LevenbergMarquardt(ConstantDamping(1e-3), num_iters=100).eval()
    alone = solver(problem, T_init)
    assert alone.failed.tolist() == [False, False, True]
    body = solver(problem, T_init, bodies=Bodies(torch.zeros(3, dtype=torch.long), C))
    assert not bool(body.failed.any())
    dR, dt = body.body_pose.magnitude()
    assert float(dt[0]) < 2e-3 and float(dR[0]) < 0.05, (float(dt[0]), float(dR[0]))
    torch.testing.assert_close(body.pose.data, (C @ body.body_pose.expand(3)).data)
    assert len(set(body.iterations.tolist())) == 1


def test_bodies_in_one_batch_are_solved_independently():
    """Two rigs in one batch end where each ends alone."""
    p1, C = rig_problem(3, 100, seed=1)
    p2, _ = rig_problem(3, 100, seed=2)
    both = FeaturemetricProblem(torch.cat([p1.p3d_world, p2.p3d_world]), torch.cat([p1.F_ref, p2.F_ref]),
                                torch.cat([p1.F_query, p2.F_query]), type(p1.camera).cat([p1.camera, p2.camera]),
                                torch.cat([p1.W_ref, p2.W_ref]), torch.cat([p1.W_query, p2.W_query]))
    starts = [Pose.exp(torch.tensor(x)).reshape(1)
              for x in ([0.02, 0, 0.01, 0.0, 0.01, 0], [-0.01, 0.02, 0, 0.01, 0, 0])]
    solver = LevenbergMarquardt(ConstantDamping(1e-3), num_iters=100).eval()
    ones = [solver(p, C @ s.expand(3), bodies=Bodies(torch.zeros(3, dtype=torch.long), C))
            for p, s in zip((p1, p2), starts)]
    joint = solver(both, Pose.cat([C @ s.expand(3) for s in starts]),
                   bodies=Bodies(torch.tensor([0, 0, 0, 1, 1, 1]), Pose.cat([C, C])))
    torch.testing.assert_close(joint.body_pose.data, Pose.cat([o.body_pose for o in ones]).data, atol=1e-5, rtol=0)
    assert joint.iterations.tolist() == [int(o.iterations[0]) for o in ones for _ in range(3)]


def test_bodies_are_checked():
    import pytest
    with pytest.raises(ValueError, match="each with at least one problem"):
        Bodies(torch.tensor([0, 2]), Pose.identity(2))
    with pytest.raises(ValueError, match="cam_from_body"):
        Bodies(torch.tensor([0, 0]), Pose.identity(3))
    assert Bodies.of(["b", "a", "b"], Pose.identity(3)).index.tolist() == [0, 1, 0]


def test_a_bodys_uncertainty_adds_its_cameras_information():
    """``alignment_uncertainty`` with bodies: a body of one camera at the identity has that camera's sigma; a rig's
    three cameras pin its pose down better than any of them alone."""
    from pixloc.optim import alignment_uncertainty
    problem, C = rig_problem(3, 150, seed=4)
    solver = LevenbergMarquardt(ConstantDamping(1e-3)).eval()
    own = alignment_uncertainty(problem, C, solver.loss_fn, solver.interpolator,
                                bodies=Bodies(torch.arange(3), Pose.identity(3)))
    torch.testing.assert_close(own["body_sigma"], own["sigma"], rtol=1e-3, atol=1e-6)
    rig = alignment_uncertainty(problem, C, solver.loss_fn, solver.interpolator,
                                bodies=Bodies(torch.zeros(3, dtype=torch.long), C))
    assert len(set(rig["body_sigma"].tolist())) == 1
    assert float(rig["body_sigma"][0]) < float(rig["sigma"].min()), (rig["body_sigma"], rig["sigma"])
