"""Batched rigid transforms, named like pycolmap: ``cam_from_world``."""

from typing import Tuple

import numpy as np
import torch
from torch import Tensor

from . import lie
from .wrapper import TensorWrapper


class Pose(TensorWrapper):
    """A batch of SE(3) transforms ``b_from_a``, stored as (..., 12) = [R (row-major), t].

    Transforms points as ``p_b = R p_a + t`` (COLMAP's ``cam_from_world``).
    Compose right to left: ``c_from_a = c_from_b @ b_from_a``.
    """

    def __init__(self, data: Tensor):
        if data.shape[-1] != 12:
            raise ValueError(f"Pose data must have 12 values in its last dim, got shape {tuple(data.shape)}.")
        super().__init__(data)

    @classmethod
    def from_Rt(cls, R, t) -> "Pose":
        """R: (..., 3, 3) rotation matrices; t: (..., 3) translations."""
        R, t = torch.as_tensor(R), torch.as_tensor(t)
        if R.shape[-2:] != (3, 3) or t.shape[-1] != 3 or R.shape[:-2] != t.shape[:-1]:
            raise ValueError(f"Pose.from_Rt expects R (..., 3, 3) and t (..., 3), "
                             f"got {tuple(R.shape)} and {tuple(t.shape)}.")
        dtype = torch.promote_types(R.dtype, t.dtype)
        if not dtype.is_floating_point:
            dtype = torch.get_default_dtype()
        return cls(torch.cat([R.to(dtype).flatten(-2), t.to(dtype)], -1))

    @classmethod
    def from_4x4(cls, T) -> "Pose":
        """T: (..., 4, 4) homogeneous matrices."""
        T = torch.as_tensor(T)
        if T.shape[-2:] != (4, 4):
            raise ValueError(f"Pose.from_4x4 expects (..., 4, 4), got {tuple(T.shape)}.")
        return cls.from_Rt(T[..., :3, :3], T[..., :3, 3])

    @classmethod
    def from_aa(cls, w: Tensor, t: Tensor) -> "Pose":
        """Rotation exp(w) (axis-angle, radians) and translation t, both (..., 3).

        This is the official PixLoc pose update (not the full SE(3) exp): the
        translation is used as is.
        """
        return cls.from_Rt(lie.so3_exp_first_order(w), t)

    @classmethod
    def exp(cls, xi: Tensor) -> "Pose":
        """SE(3) exponential of xi: (..., 6) = (rho, w)."""
        return cls.from_Rt(*lie.se3_exp(xi))

    @classmethod
    def from_qvec(cls, qvec, tvec) -> "Pose":
        """From COLMAP quaternions (w, x, y, z) (..., 4) and translations (..., 3)."""
        qvec, tvec = torch.as_tensor(qvec), torch.as_tensor(tvec)
        return cls.from_Rt(lie.qvec_to_rotmat(qvec), tvec)

    @classmethod
    def identity(cls, *shape, dtype=None, device=None) -> "Pose":
        R = torch.eye(3, dtype=dtype, device=device).expand(*shape, 3, 3)
        t = torch.zeros(*shape, 3, dtype=dtype, device=device)
        return cls.from_Rt(R, t)

    @property
    def R(self) -> Tensor:
        """(..., 3, 3) rotation matrices."""
        return self._data[..., :9].reshape(self._data.shape[:-1] + (3, 3))

    @property
    def t(self) -> Tensor:
        """(..., 3) translations."""
        return self._data[..., -3:]

    @property
    def qvec(self) -> Tensor:
        """(..., 4) COLMAP quaternions (w, x, y, z), w >= 0."""
        return lie.rotmat_to_qvec(self.R)

    @property
    def center(self) -> Tensor:
        """(..., 3) position of the origin of frame b in frame a: -R^T t."""
        return -(self.R.transpose(-1, -2) @ self.t[..., None])[..., 0]

    def matrix(self) -> Tensor:
        """(..., 4, 4) homogeneous matrices."""
        bottom = torch.zeros(self.shape + (1, 4), dtype=self.dtype, device=self.device)
        bottom[..., 0, 3] = 1
        return torch.cat([torch.cat([self.R, self.t[..., None]], -1), bottom], -2)

    def inv(self) -> "Pose":
        """a_from_b from b_from_a."""
        Rt = self.R.transpose(-1, -2)
        return Pose.from_Rt(Rt, -(Rt @ self.t[..., None])[..., 0])

    def __matmul__(self, other: "Pose") -> "Pose":
        """c_from_a = c_from_b @ b_from_a, broadcasting batch shapes."""
        if not isinstance(other, Pose):
            return NotImplemented
        R = self.R @ other.R
        t = self.t + (self.R @ other.t[..., None])[..., 0]
        return Pose.from_Rt(R, t)

    def transform(self, p3d: Tensor) -> Tensor:
        """p3d: (..., N, 3) points in frame a -> (..., N, 3) in frame b."""
        if p3d.shape[-1] != 3:
            raise ValueError(f"Points must have shape (..., N, 3), got {tuple(p3d.shape)}.")
        return p3d @ self.R.transpose(-1, -2) + self.t[..., None, :]

    def __mul__(self, p3d: Tensor) -> Tensor:
        return self.transform(p3d)

    def J_transform(self, p3d_out: Tensor) -> Tensor:
        """Jacobian of the transformed points w.r.t. a left update of the pose.

        With ``T <- exp(delta) @ T`` and delta = (dt, dw), d(T p)/d delta at 0
        is [I | -[T p]x]. p3d_out: (..., N, 3), already transformed -> (..., N, 3, 6).
        """
        eye = torch.eye(3, dtype=p3d_out.dtype, device=p3d_out.device).expand(p3d_out.shape + (3,))
        return torch.cat([eye, -lie.skew(p3d_out)], -1)

    @staticmethod
    def J_left(J: Tensor, p3d_out: Tensor) -> Tensor:
        """``J @ J_transform(p3d_out)`` for a Jacobian J (..., N, K, 3) at the transformed points, without
        the (..., N, 3, 6) factor: [J | rows p x J_k], since J_k . (-[p]x u) = (p x J_k) . u. Elementwise,
        where the product is K x 6 matrices of 3 terms each (an LM iteration's, 2 x 6 per point)."""
        return torch.cat([J, torch.linalg.cross(p3d_out[..., None, :].expand_as(J), J, dim=-1)], -1)

    def log(self) -> Tensor:
        """(..., 6) = (rho, w), inverse of ``Pose.exp``."""
        return lie.se3_log(self.R, self.t)

    def magnitude(self) -> Tuple[Tensor, Tensor]:
        """Rotation angle in degrees and translation norm, each (...).

        The angle is computed stably (atan2), unlike the official acos.
        """
        return torch.rad2deg(lie.rotation_angle(self.R)), self.t.norm(dim=-1)

    def numpy(self) -> Tuple[np.ndarray, np.ndarray]:
        return self.R.detach().cpu().numpy(), self.t.detach().cpu().numpy()

    @classmethod
    def from_matrix(cls, T, dtype=torch.float64) -> "Pose":
        """A pose from a (..., 3, 4) [R | t] (or (..., 4, 4)) array: the one numpy entry point."""
        T = torch.as_tensor(np.asarray(T, np.float64)).to(dtype)
        return cls.from_Rt(T[..., :3, :3], T[..., :3, 3])

    def to_matrix(self, orthonormal: bool = False) -> np.ndarray:
        """(..., 3, 4) float64 [R | t], the numpy exit point. ``orthonormal`` projects R back onto
        SO(3) (hundreds of float32 LM updates leave it slightly off; one pose, (3, 4), only)."""
        R, t = self.R.detach().cpu().double().numpy(), self.t.detach().cpu().double().numpy()
        if orthonormal:
            U, _, Vt = np.linalg.svd(R)
            R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        return np.concatenate([R, t[..., None]], -1)


def pose_error(T_a: Pose, T_b: Pose) -> Tuple[Tensor, Tensor]:
    """Rotation error (degrees) and camera-centre distance between cam_from_world poses.

    Returns two (...) tensors; the translation error is in scene units.
    """
    dR, _ = (T_a @ T_b.inv()).magnitude()
    dt = (T_a.center - T_b.center).norm(dim=-1)
    return dR, dt


def relative_motion(a, b, scale: float) -> Tuple[float, float]:
    """(camera-centre distance over ``scale``, rotation in degrees) between two cam_from_world poses
    given as 3 x 4 matrices: ``pose_error`` in the scale-free terms of pose verification."""
    dR, dt = pose_error(Pose.from_matrix(a), Pose.from_matrix(b))
    return float(dt) / scale, float(dR)
