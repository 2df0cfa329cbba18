"""SO(3) and SE(3) maps, in float32 or float64, batched over leading dims.

Conventions: a tangent vector of SE(3) is ``(t, w)``, translation first, as in
the official PixLoc solver. Small angles use Taylor expansions so that values
and autograd gradients stay finite at zero.
"""

import torch
from torch import Tensor


def skew(v: Tensor) -> Tensor:
    """Skew-symmetric matrices [v]x such that [v]x @ u = v x u.

    v: (..., 3) -> (..., 3, 3)
    """
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(v.shape[:-1] + (3, 3))


def _small_angle_eps(dtype: torch.dtype) -> float:
    return 1e-3 if dtype in (torch.float16, torch.bfloat16, torch.float32) else 1e-6


def so3_exp(w: Tensor) -> Tensor:
    """Rodrigues' formula: rotation matrices from axis-angle vectors.

    w: (..., 3) axis times angle in radians -> (..., 3, 3)
    """
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]  # ... x 1 x 1
    small = theta2 < _small_angle_eps(w.dtype) ** 2
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2_safe)
    W = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a * W + b * (W @ W)


def so3_exp_first_order(w: Tensor) -> Tensor:
    """The official PixLoc ``so3exp_map``: Rodrigues, but I + [w]x below 1e-7 rad.

    Kept separate so that the solver can reproduce the official update
    bit for bit; differs from ``so3_exp`` by O(theta^2) only below 1e-7 rad.
    """
    theta = w.norm(dim=-1, keepdim=True)
    small = theta < 1e-7
    div = torch.where(small, torch.ones_like(theta), theta)
    W = skew(w / div)
    theta = theta[..., None]
    res = W * torch.sin(theta) + (W @ W) * (1 - torch.cos(theta))
    res = torch.where(small[..., None], W, res)
    return torch.eye(3, dtype=w.dtype, device=w.device) + res


def rotation_angle(R: Tensor) -> Tensor:
    """Angle of rotation matrices in radians, stable near 0 and pi.

    Uses atan2(|sin|, cos) with sin from the skew part, instead of
    acos((trace - 1) / 2), which loses all precision for small angles.
    R: (..., 3, 3) -> (...)
    """
    cos = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    vee = torch.stack([R[..., 2, 1] - R[..., 1, 2],
                       R[..., 0, 2] - R[..., 2, 0],
                       R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = vee.norm(dim=-1) / 2
    return torch.atan2(sin, cos)


def so3_log(R: Tensor) -> Tensor:
    """Axis-angle vectors of rotation matrices, the inverse of ``so3_exp``.

    Stable for small angles (first-order series) and near pi (axis from the
    symmetric part). R: (..., 3, 3) -> (..., 3)
    """
    vee = torch.stack([R[..., 2, 1] - R[..., 1, 2],
                       R[..., 0, 2] - R[..., 2, 0],
                       R[..., 1, 0] - R[..., 0, 1]], -1)
    theta = rotation_angle(R)[..., None]
    sin = torch.sin(theta)
    small = theta < _small_angle_eps(R.dtype)
    near_pi = (torch.pi - theta) < 1e-2
    sin_safe = torch.where(small | near_pi, torch.ones_like(sin), sin)
    scale = torch.where(small, 0.5 + theta ** 2 / 12, theta / (2 * sin_safe))
    w = scale * vee
    # Near pi, sin -> 0: recover the axis from R + R^T = 2 (I + (1 - cos) [n]x^2)
    # = 2 cos I + 2 (1 - cos) n n^T. Take the largest diagonal for stability.
    cos = torch.cos(theta)
    B = (R + R.transpose(-1, -2)) / 2
    diag = B.diagonal(dim1=-2, dim2=-1)
    nn = ((diag - cos) / (1 - cos).clamp(min=1e-12)).clamp(min=0)
    k = nn.argmax(-1, keepdim=True)
    col = torch.gather(B, -1, k[..., None].expand(B.shape[:-1] + (1,)))[..., 0]
    nk = torch.gather(nn, -1, k).sqrt().clamp(min=1e-12)
    axis = (col - cos * torch.nn.functional.one_hot(k[..., 0], 3).to(R.dtype)) / (
        (1 - cos).clamp(min=1e-12) * nk)
    axis = torch.nn.functional.normalize(axis, dim=-1)
    # The sign of the axis is fixed by the (small) skew part.
    sign = torch.where((axis * vee).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(R.dtype)
    w_pi = sign * axis * theta
    return torch.where(near_pi, w_pi, w)


def _se3_V(w: Tensor) -> Tensor:
    """Left Jacobian of SO(3): t = V rho in exp_SE3. w: (..., 3) -> (..., 3, 3)."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    small = theta2 < _small_angle_eps(w.dtype) ** 2
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2_safe)
    c = torch.where(small, 1 / 6 - theta2 / 120,
                    (theta - torch.sin(theta)) / (theta2_safe * theta))
    W = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + b * W + c * (W @ W)


def se3_exp(xi: Tensor) -> tuple[Tensor, Tensor]:
    """Exponential map of SE(3). xi: (..., 6) = (rho, w) -> R (..., 3, 3), t (..., 3)."""
    rho, w = xi.split([3, 3], dim=-1)
    return so3_exp(w), (_se3_V(w) @ rho[..., None])[..., 0]


def se3_log(R: Tensor, t: Tensor) -> Tensor:
    """Logarithm of SE(3), inverse of ``se3_exp``. -> (..., 6) = (rho, w)."""
    w = so3_log(R)
    rho = torch.linalg.solve(_se3_V(w), t[..., None])[..., 0]
    return torch.cat([rho, w], -1)


def qvec_to_rotmat(q: Tensor) -> Tensor:
    """Rotation matrices from unit quaternions in COLMAP order (w, x, y, z).

    q: (..., 4), normalised here -> (..., 3, 3)
    """
    w, x, y, z = torch.nn.functional.normalize(q, dim=-1).unbind(-1)
    R = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)
    return R.reshape(q.shape[:-1] + (3, 3))


def rotmat_to_qvec(R: Tensor) -> Tensor:
    """Unit quaternions (w, x, y, z), w >= 0, from rotation matrices (Shepperd's method).

    R: (..., 3, 3) -> (..., 4)
    """
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack([
        torch.stack([1 + tr, m[..., 2, 1] - m[..., 1, 2],
                     m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                     m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0],
                     1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0],
                     m[..., 1, 2] + m[..., 2, 1], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1),
    ], -2)  # ... x 4 candidates x 4
    # Each candidate is 4 q_k q; pick the one with the largest |q_k|.
    k = torch.stack([1 + tr, 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                     1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                     1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1).argmax(-1)
    q = torch.gather(cands, -2, k[..., None, None].expand(k.shape + (1, 4)))[..., 0, :]
    q = torch.nn.functional.normalize(q, dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)
