"""How well a pose explains a featuremetric problem: the evidence that pose verification reads.

The LM cost alone cannot tell a converged pose from a wrong one (its value depends on the
scene, the level and how many points stay valid), so the evidence is counted the way the
robust loss sees the residuals: a point is an *inlier* at a pose when it projects validly
and its robust weight rho'(|r|^2) is at least one half (for official PixLoc's
``scaled_barron(0, 0.1)``, |r|^2 <= 0.02 on L2-normalised features). Fractions are over all
the problem's points, so points that leave the image count against a pose.
"""

from typing import Callable, Dict, Optional

import torch
from torch import Tensor

from ..geometry import Pose
from ..interpolation import Interpolator
from .bodies import Bodies
from .cost import FeaturemetricProblem, build_system, linearize, robust_weights


def _costs(problem: FeaturemetricProblem, cam_from_world: Pose, loss_fn: Callable, interpolator: Interpolator):
    """Per point at a pose: robust cost rho, its weight rho', validity (inside the margin, in front
    of the camera, not padding), the sampled query values (with the confidence channel if any),
    the points in the camera frame and their projections."""
    p3d = cam_from_world.transform(problem.p3d_world)
    p2d, visible = problem.camera.cam2image(p3d)
    values, valid, _ = interpolator(problem.maps_at(p2d, gradients=False), p2d, gradients=False)
    if problem.mask is not None:
        valid = valid & problem.mask
    C = problem.F_ref.shape[-1]
    rho, weight, _ = loss_fn(((values[..., :C] - problem.F_ref) ** 2).sum(-1))
    return rho, weight, valid & visible, values, p3d, p2d


def _mask(problem: FeaturemetricProblem) -> Tensor:
    if problem.mask is not None:
        return problem.mask
    return torch.ones(problem.p3d_world.shape[:2], dtype=torch.bool, device=problem.p3d_world.device)


@torch.no_grad()
def alignment_evidence(problem: FeaturemetricProblem, cam_from_world: Pose, loss_fn: Callable,
                       interpolator: Interpolator, inlier_weight: float = 0.5) -> Dict[str, Tensor]:
    """Per problem (B,): ``points`` (masked points N_b), ``valid`` (fraction projecting inside the
    margin), ``inliers`` (fraction that are inliers of the robust loss), ``weighted_inliers``
    (confidence-weighted inlier fraction, 0..1 relative to the confidence of all points) and
    ``cost`` (mean robust cost over valid points, as the solver reports it)."""
    rho, weight, valid, values, _, _ = _costs(problem, cam_from_world, loss_fn, interpolator)
    mask = _mask(problem)
    inlier = valid & (weight >= inlier_weight)
    n = mask.sum(-1).clamp(min=1).to(rho.dtype)
    if problem.W_ref is not None:
        C = problem.F_ref.shape[-1]
        w_all = problem.W_ref.masked_fill(~mask, 0.0)
        w_inl = (problem.W_ref * values[..., C]).masked_fill(~inlier, 0.0)
        weighted = w_inl.sum(-1) / w_all.sum(-1).clamp(min=1e-12)
    else:
        weighted = inlier.sum(-1) / n
    num_valid = valid.sum(-1)
    return {"points": mask.sum(-1), "valid": num_valid / n, "inliers": inlier.sum(-1) / n,
            "weighted_inliers": weighted,
            "cost": (rho * valid).sum(-1) / num_valid.clamp(min=1)}


def _contrast_around(problem: FeaturemetricProblem, cam_from_world: Pose, steps, loss_fn: Callable,
                     interpolator: Interpolator) -> Tensor:
    """(B,) 1 - cost at the pose / mean cost at ``step @ pose`` for each step, over the points valid
    at all of them (0 where none is)."""
    rho0, _, valid, _, _, _ = _costs(problem, cam_from_world, loss_fn, interpolator)
    around = []
    for step in steps:
        rho, _, v, _, _, _ = _costs(problem, step @ cam_from_world, loss_fn, interpolator)
        around.append(rho)
        valid = valid & v
    n = valid.sum(-1).clamp(min=1)
    c0 = (rho0 * valid).sum(-1) / n
    mean_around = torch.stack([(r * valid).sum(-1) / n for r in around]).mean(0)
    out = 1 - c0 / mean_around.clamp(min=1e-12)
    return torch.where(valid.sum(-1) > 0, out, torch.zeros_like(out))


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
    angle = shift_px / problem.camera.f.mean(-1)  # B
    zero = torch.zeros_like(angle)
    steps = []
    for axis in range(2):
        for sign in (1.0, -1.0):
            w = torch.stack([sign * angle if axis == 0 else zero, sign * angle if axis == 1 else zero, zero], -1)
            steps.append(Pose.from_aa(w, torch.zeros_like(w)))
    return _contrast_around(problem, cam_from_world, steps, loss_fn, interpolator)


@torch.no_grad()
def alignment_depth_contrast(problem: FeaturemetricProblem, cam_from_world: Pose, loss_fn: Callable,
                             interpolator: Interpolator, shift_px: float = 3.0) -> Tensor:
    """(B,) as ``alignment_contrast``, for the camera moved forward and backward along its axis by
    the distance that moves the median point ``shift_px`` pixels in the image (radially). Meant for
    poses wrong along the viewing direction, which small turns hardly see; on the shared scenes it
    did not separate them (docs/verification.md), so verification does not use it."""
    _, _, valid, _, p3d, p2d = _costs(problem, cam_from_world, loss_fn, interpolator)
    nan = torch.tensor(float("nan"), dtype=p2d.dtype, device=p2d.device)
    radius = torch.where(valid, (p2d - problem.camera.c[..., None, :]).norm(dim=-1), nan).nanmedian(-1).values
    depth = torch.where(valid, p3d[..., 2], nan).nanmedian(-1).values
    dz = torch.nan_to_num(shift_px * depth / radius.clamp(min=1.0), nan=0.0)  # B
    zero = torch.zeros_like(dz)
    steps = [Pose.from_aa(torch.zeros(len(dz), 3, dtype=dz.dtype, device=dz.device),
                          torch.stack([zero, zero, sign * dz], -1)) for sign in (1.0, -1.0)]
    return _contrast_around(problem, cam_from_world, steps, loss_fn, interpolator)


@torch.no_grad()
def alignment_uncertainty(problem: FeaturemetricProblem, cam_from_world: Pose, loss_fn: Callable,
                          interpolator: Interpolator, unit_t: float = 0.01, unit_R: float = 1.0,
                          bodies: Optional[Bodies] = None) -> Dict[str, Tensor]:
    """(B,) how well the featuremetric cost pins the pose down, from the Gauss-Newton Hessian H of the
    robust, confidence-weighted cost at ``cam_from_world``: the covariance s^2 H^-1 of the left
    update (dt, dw), s^2 the weighted residual variance per channel. ``sigma``: the standard deviation
    along the least-determined direction of the pose, in units of ``unit_t`` x the median point depth
    (camera centre) and ``unit_R`` degrees (rotation); ``sigma_t``: that of the camera centre alone,
    over the median point depth; ``sigma_R``: that of the rotation alone, in degrees.

    A pose that can slide (a camera on a ring around a texture-poor object, turning to keep it in
    view) has a large ``sigma`` even where the cost is sharp for image shifts (the contrast).
    Residuals of neighbouring points are correlated, so these are not calibrated probabilities:
    thresholds are measured (docs/verification.md, where pixel units separated worse).

    With ``bodies`` (``pixloc.optim.bodies``), also ``body_sigma``, ``body_sigma_t`` and ``body_sigma_R`` of
    each problem's body: its cameras' information (inverse covariances) moved to the body's update through their
    adjoints and summed, the depth the median of its cameras' (a direction one camera leaves free, another may
    pin down)."""
    # one problem at a time: the Jacobians of a whole batch of dense problems would double the peak memory
    covs, depths = zip(*(_covariance(problem.index(b), cam_from_world[b:b + 1], loss_fn, interpolator)
                         for b in range(problem.batch_size)))
    cov, depth = torch.cat(covs), torch.cat(depths)
    out = _sigmas(cov, depth, unit_t, unit_R)
    if bodies is not None:  # the information of a body's cameras, through their adjoints, summed
        A = bodies.adjoint.to(cov)
        index = bodies.index.to(cov.device)
        info = A.transpose(-1, -2) @ torch.linalg.pinv(cov) @ A
        info = info.new_zeros(bodies.num_bodies, 6, 6).index_add_(0, index, info)
        body_depth = torch.stack([depth[index == k].median() for k in range(bodies.num_bodies)])
        out.update({f"body_{k}": bodies.spread(v) for k, v in
                    _sigmas(torch.linalg.pinv(info), body_depth, unit_t, unit_R).items()})
    return out


def _sigmas(cov: Tensor, depth: Tensor, unit_t: float, unit_R: float) -> Dict[str, Tensor]:
    """``sigma``, ``sigma_t``, ``sigma_R`` of covariances (B, 6, 6) of a left update (dt, dw) and the
    median point depths (B,) (``alignment_uncertainty``)."""
    unit = torch.cat([(unit_t * depth)[:, None].expand(-1, 3),
                      torch.full_like(depth, unit_R * torch.pi / 180)[:, None].expand(-1, 3)], -1)

    def top(c: Tensor) -> Tensor:  # the standard deviation along the least-determined direction
        return torch.linalg.eigvalsh(c)[..., -1].clamp(min=0).sqrt()

    return {"sigma": top(cov / unit[:, :, None] / unit[:, None, :]).float(),
            "sigma_t": (top(cov[:, :3, :3]) / depth).float(),
            "sigma_R": torch.rad2deg(top(cov[:, 3:, 3:])).float()}


def _covariance(problem: FeaturemetricProblem, cam_from_world: Pose, loss_fn: Callable, interpolator: Interpolator):
    """(covariance s^2 H^-1 of the left update (dt, dw), median depth of the valid points), float64, per problem."""
    lin = linearize(cam_from_world, problem, interpolator)
    _, weights = robust_weights(lin, loss_fn)
    _, H = build_system(lin, weights)
    m = lin.valid.sum(-1) * problem.F_ref.shape[-1]
    s2 = (weights * lin.sq).sum(-1).double() / (m - 6).clamp(min=1)
    p3d = cam_from_world.transform(problem.p3d_world)
    z = torch.where(lin.valid, p3d[..., 2], torch.full_like(p3d[..., 2], float("nan")))
    depth = torch.nan_to_num(z.nanmedian(-1).values.double(), nan=1.0).clamp(min=1e-9)
    return s2[:, None, None] * torch.linalg.pinv(H.double()), depth
