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
