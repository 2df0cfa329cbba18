"""Lens distortion models on normalized image coordinates, with analytic Jacobians.

Each model maps undistorted normalized points p = (x/z, y/z) to distorted
ones and says where the model is valid. Parameters follow COLMAP's order.
All functions take p: (..., N, 2) and params: (..., D) and return
(p_distorted (..., N, 2), valid (..., N)); the Jacobians d p_d / d p are
(..., N, 2, 2).
"""

from typing import Any, Callable, Dict, NamedTuple, Optional, Tuple

import torch
from torch import Tensor


def _none(p: Tensor, d: Tensor) -> Tuple[Tensor, Tensor]:
    return p, torch.ones(p.shape[:-1], dtype=torch.bool, device=p.device)


def _J_none(p: Tensor, d: Tensor) -> Tensor:
    return torch.eye(2, dtype=p.dtype, device=p.device).expand(p.shape + (2,))


def _tangential(p: Tensor, p12: Tensor, r2: Tensor) -> Tensor:
    uv = p.prod(-1, keepdim=True)
    return 2 * p12 * uv + p12.flip(-1) * (r2 + 2 * p ** 2)


def _J_tangential(p: Tensor, p12: Tensor) -> Tuple[Tensor, Tensor]:
    p21 = p12.flip(-1)
    return 2 * p12 * p.flip(-1) + 6 * p21 * p, 2 * p12 * p + 2 * p21 * p.flip(-1)


def _assemble(J_diag: Tensor, J_cross: Tensor) -> Tensor:
    # [[dx'/dx, dx'/dy], [dy'/dx, dy'/dy]] from diagonal and cross terms.
    return torch.diag_embed(J_diag) + torch.diag_embed(J_cross).flip(-1)


def _radial_limit(d: Tensor) -> Tuple[Tensor, Tensor]:
    """Where the RADIAL and OPENCV models are valid, from their parameters d (..., D) alone: (limited,
    limit) (..., 1, 1), a point valid where not limited or r^2 < limit.

    Beyond the inflection point of r (1 + k1 r^2 + k2 r^4), far points fold back into the image:
    official PixLoc rejects r^2 above a root of 1 + 3 k1 r^2 + 5 k2 r^4 = 0. Its exact cases are kept
    (the root (sqrt(9 k1^2 - 20 k2) - 3 k1) / (10 k2), no limit for k1 < 0 with k2 = 0, 1 / (3 k1)
    for k1 > 0 with k2 <= 0) so that validity masks, hence LM steps, match the official ones."""
    d = d[..., None, :]
    k1, k2 = d[..., 0:1], d[..., 1:2]
    limited = ((k2 > 0) & ((9 * k1 ** 2 - 20 * k2) > 0)) | ((k2 <= 0) & (k1 > 0))
    k2_safe = torch.where(k2 > 0, k2, torch.ones_like(k2))
    k1_safe = torch.where(k1 == 0, torch.ones_like(k1), k1)
    disc = (9 * k1 ** 2 - 20 * k2).clamp(min=0)
    limit = torch.abs(torch.where(
        k2 > 0, (torch.sqrt(disc) - 3 * k1) / (10 * k2_safe), 1 / (3 * k1_safe)))
    return limited, limit


def _radial_tangential(p: Tensor, d: Tensor, limits: Optional[Tuple[Tensor, Tensor]] = None
                       ) -> Tuple[Tensor, Tensor]:
    """RADIAL (k1, k2) and OPENCV (k1, k2, p1, p2), as official PixLoc. ``limits``: ``_radial_limit(d)``
    if already computed (a camera keeps it: ``Camera.distort``)."""
    limited, limit = _radial_limit(d) if limits is None else limits
    d = d[..., None, :]
    k1, k2 = d[..., 0:1], d[..., 1:2]
    r2 = (p ** 2).sum(-1, keepdim=True)
    out = p + p * (k1 * r2 + k2 * r2 ** 2)
    valid = (~limited | (r2 < limit))[..., 0]
    if d.shape[-1] > 2:
        out = out + _tangential(p, d[..., 2:4], r2)
    return out, valid


def _J_radial_tangential(p: Tensor, d: Tensor) -> Tensor:
    d = d[..., None, :]
    k1, k2 = d[..., 0:1], d[..., 1:2]
    r2 = (p ** 2).sum(-1, keepdim=True)
    uv = p.prod(-1, keepdim=True)
    radial = k1 * r2 + k2 * r2 ** 2
    d_radial = 2 * k1 + 4 * k2 * r2
    J_diag = 1 + radial + p ** 2 * d_radial
    J_cross = uv * d_radial
    if d.shape[-1] > 2:
        jd, jc = _J_tangential(p, d[..., 2:4])
        J_diag, J_cross = J_diag + jd, J_cross + jc
    return _assemble(J_diag.expand(p.shape), J_cross.expand(p.shape))


def _full_opencv(p: Tensor, d: Tensor) -> Tuple[Tensor, Tensor]:
    """FULL_OPENCV (k1, k2, p1, p2, k3, k4, k5, k6): rational radial model."""
    d = d[..., None, :]
    k1, k2, p12, k3, k4, k5, k6 = (d[..., 0:1], d[..., 1:2], d[..., 2:4], d[..., 4:5],
                                   d[..., 5:6], d[..., 6:7], d[..., 7:8])
    r2 = (p ** 2).sum(-1, keepdim=True)
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    out = p * num / den + _tangential(p, p12, r2)
    # Valid while r * radial(r) still increases with r and the denominator
    # has not crossed zero (no closed form for the first root here).
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    d_rr = num / den + 2 * r2 * (dnum * den - num * dden) / den ** 2
    valid = ((d_rr > 0) & (den > 0))[..., 0]
    return out, valid


def _J_full_opencv(p: Tensor, d: Tensor) -> Tensor:
    d = d[..., None, :]
    k1, k2, p12, k3, k4, k5, k6 = (d[..., 0:1], d[..., 1:2], d[..., 2:4], d[..., 4:5],
                                   d[..., 5:6], d[..., 6:7], d[..., 7:8])
    r2 = (p ** 2).sum(-1, keepdim=True)
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d num / d r2
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    radial = num / den
    d_radial = 2 * (dnum * den - num * dden) / den ** 2  # d radial / d r2, times 2
    J_diag = radial + p ** 2 * d_radial
    J_cross = p.prod(-1, keepdim=True) * d_radial
    jd, jc = _J_tangential(p, p12)
    return _assemble(J_diag + jd, (J_cross + jc).expand(p.shape))


def _fisheye_terms(p: Tensor, d: Tensor):
    d = d[..., None, :]
    k1, k2, k3, k4 = d[..., 0:1], d[..., 1:2], d[..., 2:3], d[..., 3:4]
    r2 = (p ** 2).sum(-1, keepdim=True)
    small = r2 < 1e-6
    r = torch.where(small, torch.ones_like(r2), r2).sqrt()
    theta = torch.atan(r)
    t2 = theta ** 2
    poly = 1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    dpoly = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))  # d theta_d / d theta
    return k1, r2, small, r, theta, poly, dpoly


def _fisheye(p: Tensor, d: Tensor) -> Tuple[Tensor, Tensor]:
    """OPENCV_FISHEYE (k1, k2, k3, k4): equidistant model, theta_d = theta (1 + k1 theta^2 + ...)."""
    k1, r2, small, r, theta, poly, dpoly = _fisheye_terms(p, d)
    # s = theta_d / r, with its series near the optical axis.
    s = torch.where(small, 1 + (k1 - 1 / 3) * r2, theta * poly / r)
    valid = (dpoly > 0)[..., 0]
    return p * s, valid


def _J_fisheye(p: Tensor, d: Tensor) -> Tensor:
    k1, r2, small, r, theta, poly, dpoly = _fisheye_terms(p, d)
    s = torch.where(small, 1 + (k1 - 1 / 3) * r2, theta * poly / r)
    # d s / d r divided by r, so that d s / d p = (ds/dr / r) p.
    ds_r = torch.where(small, 2 * (k1 - 1 / 3) * torch.ones_like(r2),
                       (dpoly / (1 + r ** 2) * r - theta * poly) / r ** 3)
    eye = torch.eye(2, dtype=p.dtype, device=p.device)
    return s[..., None] * eye + ds_r[..., None] * p[..., :, None] * p[..., None, :]


class DistortionModel(NamedTuple):
    num_params: int
    distort: Callable[..., Tuple[Tensor, Tensor]]
    J_distort: Callable[[Tensor, Tensor], Tensor]
    # what ``distort`` computes from the parameters alone, passed to it as a third argument where given
    prepare: Optional[Callable[[Tensor], Any]] = None


DISTORTIONS: Dict[str, DistortionModel] = {
    "none": DistortionModel(0, _none, _J_none),
    "radial": DistortionModel(2, _radial_tangential, _J_radial_tangential, _radial_limit),
    "opencv": DistortionModel(4, _radial_tangential, _J_radial_tangential, _radial_limit),
    "full_opencv": DistortionModel(8, _full_opencv, _J_full_opencv),
    "fisheye": DistortionModel(4, _fisheye, _J_fisheye),
}
