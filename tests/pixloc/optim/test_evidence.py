"""The evidence of an alignment: inliers of the robust loss and the sharpness of the cost."""

import torch

from pixloc.geometry import Pose
from pixloc.interpolation import Interpolator
from pixloc.losses import get_loss
from pixloc.optim import alignment_contrast, alignment_depth_contrast, alignment_evidence
from workflows.benchmarks.lm import make_problems


def test_the_true_pose_explains_the_points_and_sits_in_a_sharp_valley():
    problem, _ = make_problems(2, 400, 16, "cpu")  # reference features sampled at the identity pose
    loss, interp = get_loss("scaled_barron(0, 0.1)"), Interpolator("linear", 2)
    true = Pose.identity(2)
    wrong = Pose.from_aa(torch.tensor([[0.0, 0.25, 0.0]] * 2), torch.zeros(2, 3)) @ true  # ~30 px off
    at_true = alignment_evidence(problem, true, loss, interp)
    at_wrong = alignment_evidence(problem, wrong, loss, interp)
    assert (at_true["inliers"] > 0.95).all() and (at_true["cost"] < 1e-6).all()
    assert (at_wrong["inliers"] < 0.3).all()
    assert (at_true["weighted_inliers"] > at_wrong["weighted_inliers"]).all()
    sharp = alignment_contrast(problem, true, loss, interp, 3.0)
    flat = alignment_contrast(problem, wrong, loss, interp, 3.0)
    assert (sharp > 0.9).all() and (flat.abs() < 0.2).all(), (sharp, flat)
    along = alignment_depth_contrast(problem, true, loss, interp, 3.0)
    assert (along > 0.9).all() and (alignment_depth_contrast(problem, wrong, loss, interp, 3.0).abs() < 0.2).all()


def test_a_pose_the_points_pin_down_is_certain_one_that_can_slide_is_not():
    """``alignment_uncertainty``: with the same noise on the reference features, points spread over the
    image pin the pose down; the same number of points in a small patch (turning and moving the camera
    sideways shift them alike) leave it free to slide, with a standard deviation many times larger.
    Twice the noise doubles it."""
    from dataclasses import replace

    from pixloc.optim import alignment_uncertainty

    problem, _ = make_problems(1, 400, 16, "cpu")
    loss, interp = get_loss("scaled_barron(0, 0.1)"), Interpolator("linear", 2)
    noise = torch.randn(problem.F_ref.shape, generator=torch.Generator().manual_seed(1))

    def sigma(p3d, amount):  # the reference features: the query's at the points' projections, plus noise
        p2d, _ = problem.camera.cam2image(p3d)
        F_ref = interp(problem.query_maps, p2d, gradients=False)[0][..., :problem.F_ref.shape[-1]]
        noisy = replace(problem, p3d_world=p3d, F_ref=F_ref + amount * noise)
        return alignment_uncertainty(noisy, Pose.identity(1), loss, interp)

    spread = sigma(problem.p3d_world, 0.05)
    p = problem.p3d_world
    patch = p[:, :1] + 0.02 * (p - p.mean(1, keepdim=True))  # the same points squeezed around one of them
    small = sigma(patch, 0.05)
    assert set(spread) == {"sigma", "sigma_t", "sigma_R"}
    assert (spread["sigma"] > 0).all() and torch.isfinite(small["sigma"]).all()
    assert (small["sigma"] > 10 * spread["sigma"]).all(), (small, spread)
    assert torch.allclose(sigma(problem.p3d_world, 0.1)["sigma"], 2 * spread["sigma"], rtol=0.2)
