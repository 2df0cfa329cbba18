"""How well a pose explains a featuremetric problem: the evidence that pose verification reads.

The LM cost alone cannot tell a converged pose from a wrong one (its value depends on the
scene, the level and how many points stay valid), so the evidence is counted the way the
robust loss sees the residuals: a point is an *inlier* at a pose when it projects validly
and its robust weight rho'(|r|^2) is at least one half (for official PixLoc's
``scaled_barron(0, 0.1)``, |r|^2 <= 0.02 on L2-normalised features). Fractions are over all
the problem's points, so points that leave the image count against a pose.
"""

from typing import Callable, Dict

import torch
from torch import Tensor

from ..geometry import Pose
from ..interpolation import Interpolator
from .cost import FeaturemetricProblem


@torch.no_grad()
def alignment_evidence(problem: FeaturemetricProblem, cam_from_world: Pose, loss_fn: Callable,
                       interpolator: Interpolator, inlier_weight: float = 0.5) -> Dict[str, Tensor]:
    """Per problem (B,): ``points`` (masked points N_b), ``valid`` (fraction projecting inside the
    margin), ``inliers`` (fraction that are inliers of the robust loss), ``weighted_inliers``
    (confidence-weighted inlier fraction, 0..1 relative to the confidence of all points) and
    ``cost`` (mean robust cost over valid points, as the solver reports it)."""
    p3d_cam = cam_from_world.transform(problem.p3d_world)
    p2d, visible = problem.camera.cam2image(p3d_cam)
    C = problem.F_ref.shape[-1]
    values, valid, _ = interpolator(problem.query_maps, p2d, gradients=False)
    valid = valid & visible
    mask = problem.mask if problem.mask is not None else torch.ones_like(valid)
    valid = valid & mask
    rho, weight, _ = loss_fn(((values[..., :C] - problem.F_ref) ** 2).sum(-1))
    inlier = valid & (weight >= inlier_weight)
    n = mask.sum(-1).clamp(min=1).to(rho.dtype)
    if problem.W_ref is not None:
        w_all = problem.W_ref.masked_fill(~mask, 0.0)
        w_inl = (problem.W_ref * values[..., C]).masked_fill(~inlier, 0.0)
        weighted = w_inl.sum(-1) / w_all.sum(-1).clamp(min=1e-12)
    else:
        weighted = inlier.sum(-1) / n
    num_valid = valid.sum(-1)
    return {"points": mask.sum(-1), "valid": num_valid / n, "inliers": inlier.sum(-1) / n,
            "weighted_inliers": weighted,
            "cost": (rho * valid).sum(-1) / num_valid.clamp(min=1)}


@torch.no_grad()
def alignment_contrast(problem: FeaturemetricProblem, cam_from_world: Pose, loss_fn: Callable,
                       interpolator: Interpolator, shift_px: float = 3.0) -> Tensor:
    """(B,) how much sharper the cost is at ``cam_from_world`` than around it: 1 - cost(T) / mean
    cost of T turned about the camera's x and y axes by the angle that shifts the image by
    ``shift_px`` pixels (four turns). Over the points valid at all five poses, unweighted.

    A correct alignment sits in a narrow valley of the featuremetric cost (the features match
    there and not a few pixels off), so its contrast is clearly positive even when day and night
    features differ too much for many residuals to be inliers; a wrong minimum of misaligned
    features is flat (contrast near 0)."""
    C = problem.F_ref.shape[-1]
    B = problem.batch_size
    mask = problem.mask if problem.mask is not None else torch.ones(problem.p3d_world.shape[:2], dtype=torch.bool,
                                                                      device=problem.p3d_world.device)

    def costs(T: Pose):
        p2d, visible = problem.camera.cam2image(T.transform(problem.p3d_world))
        values, valid, _ = interpolator(problem.query_maps, p2d, gradients=False)
        rho, _, _ = loss_fn(((values[..., :C] - problem.F_ref) ** 2).sum(-1))
        return rho, valid & visible & mask

    rho0, valid = costs(cam_from_world)
    angle = shift_px / problem.camera.f.mean(-1)  # B
    zero = torch.zeros_like(angle)
    shifted = []
    for axis in range(2):
        for sign in (1.0, -1.0):
            w = torch.stack([sign * angle if axis == 0 else zero, sign * angle if axis == 1 else zero, zero], -1)
            rho, v = costs(Pose.from_aa(w, torch.zeros_like(w)) @ cam_from_world)
            shifted.append(rho)
            valid = valid & v
    n = valid.sum(-1).clamp(min=1)
    c0 = (rho0 * valid).sum(-1) / n
    around = torch.stack([(r * valid).sum(-1) / n for r in shifted]).mean(0)
    out = 1 - c0 / around.clamp(min=1e-12)
    return torch.where(valid.sum(-1) > 0, out, torch.zeros(B, dtype=out.dtype, device=out.device))


@torch.no_grad()
def alignment_depth_contrast(problem: FeaturemetricProblem, cam_from_world: Pose, loss_fn: Callable,
                             interpolator: Interpolator, shift_px: float = 3.0) -> Tensor:
    """(B,) as ``alignment_contrast``, for the camera moved forward and backward along its axis by
    the distance that moves the median point ``shift_px`` pixels in the image (radially). Small
    turns hardly see a pose that is wrong along the viewing direction; this does."""
    C = problem.F_ref.shape[-1]
    mask = problem.mask if problem.mask is not None else torch.ones(problem.p3d_world.shape[:2], dtype=torch.bool,
                                                                      device=problem.p3d_world.device)

    def costs(T: Pose):
        p3d = T.transform(problem.p3d_world)
        p2d, visible = problem.camera.cam2image(p3d)
        values, valid, _ = interpolator(problem.query_maps, p2d, gradients=False)
        rho, _, _ = loss_fn(((values[..., :C] - problem.F_ref) ** 2).sum(-1))
        return rho, valid & visible & mask, p3d, p2d

    rho0, valid, p3d, p2d = costs(cam_from_world)
    nan = torch.tensor(float("nan"), dtype=p2d.dtype, device=p2d.device)
    radius = torch.where(valid, (p2d - problem.camera.c[..., None, :]).norm(dim=-1), nan).nanmedian(-1).values
    depth = torch.where(valid, p3d[..., 2], nan).nanmedian(-1).values
    dz = torch.nan_to_num(shift_px * depth / radius.clamp(min=1.0), nan=0.0)  # B
    shifted = []
    for sign in (1.0, -1.0):
        t = torch.stack([torch.zeros_like(dz), torch.zeros_like(dz), sign * dz], -1)
        rho, v, _, _ = costs(Pose.from_aa(torch.zeros_like(t), t) @ cam_from_world)
        shifted.append(rho)
        valid = valid & v
    n = valid.sum(-1).clamp(min=1)
    c0 = (rho0 * valid).sum(-1) / n
    around = torch.stack([(r * valid).sum(-1) / n for r in shifted]).mean(0)
    out = 1 - c0 / around.clamp(min=1e-12)
    return torch.where(valid.sum(-1) > 0, out, torch.zeros_like(out))
