"""The reprojection error of 2D-3D matches (a PnP pose's inliers), as a second term of the LM.

A pose from PnP is supported by keypoints; the featuremetric cost by dense features. The solver
(``LevenbergMarquardt``, ``keypoints=``) minimises both, each normalised by its own residual scale:

    E(T) = E_f(T) / s_f^2 + weight x sum_j rho(|pi(T X_j) - x_j|^2 / s_k^2)

with s_f^2 the featuremetric residuals' weighted mean square at the level's start (the scale of the
LM's own weights) and s_k^2 the keypoints' mean square reprojection error at the PnP pose (``scale``,
floored: a PnP fit to a few points can be exact). rho is Cauchy's, with scale ``CAUCHY`` s_k, so that a
wrong match among the inliers pulls little. Where the features pull away from a pose that many
keypoints support, the keypoints hold it; where PnP is weak (few inliers, larger s_k), the features
decide. Residuals are in the query camera's own pixels (pixloc convention: ``x_colmap - 0.5``).
"""

from dataclasses import dataclass, replace
from typing import Optional, Tuple

from torch import Tensor

from ..geometry import Camera, Pose

CAUCHY = 3.0  # the robust loss's scale, in units of the keypoints' residual scale


@dataclass(frozen=True)
class KeypointTerm:
    """B problems' matches: p3d (B, M, 3) world points, p2d (B, M, 2) their keypoints in ``camera``'s
    pixels, camera (B,), scale (B,) the residual scale s_k in pixels, mask (B, M) the real matches
    (padding of ragged batches), weight (B,): the term's weight (0: the features alone)."""

    p3d: Tensor
    p2d: Tensor
    camera: Camera
    scale: Tensor
    mask: Tensor
    weight: Tensor

    def __post_init__(self):
        B, M = self.p3d.shape[:2]
        if self.p3d.shape != (B, M, 3) or self.p2d.shape != (B, M, 2) or self.mask.shape != (B, M) \
                or self.scale.shape != (B,) or self.weight.shape != (B,) or tuple(self.camera.shape) != (B,):
            raise ValueError(f"KeypointTerm: p3d (B, M, 3), p2d (B, M, 2), mask (B, M), scale, weight and camera "
                             f"(B,); got {tuple(self.p3d.shape)}, {tuple(self.p2d.shape)}, {tuple(self.mask.shape)}, "
                             f"{tuple(self.scale.shape)}, {tuple(self.weight.shape)}, {tuple(self.camera.shape)}.")
        if not bool(self.scale.gt(0).all()):
            raise ValueError("KeypointTerm: the residual scales must be positive.")

    def index(self, i) -> "KeypointTerm":
        return replace(self, p3d=self.p3d[i], p2d=self.p2d[i], camera=self.camera[i], scale=self.scale[i],
                       mask=self.mask[i], weight=self.weight[i])

    def to(self, *args, **kwargs) -> "KeypointTerm":
        return KeypointTerm(self.p3d.to(*args, **kwargs), self.p2d.to(*args, **kwargs),
                            self.camera.to(*args, **kwargs), self.scale.to(*args, **kwargs),
                            self.mask.to(*args, **kwargs), self.weight.to(*args, **kwargs))

    def residuals(self, T: Pose) -> Tuple[Tensor, Tensor, Tensor]:
        """At poses T (B,): normalised residuals (B, M, 2) (pixels / s_k), their Jacobian w.r.t. a left
        update of T (B, M, 2, 6), and validity (B, M): a real match in front of the camera (a match
        projected outside the image still counts: it is evidence, not a feature sample)."""
        p_cam = T.transform(self.p3d)
        p2d, J_cam = self.camera.cam2image_with_J(p_cam)[::2]
        valid = self.mask & (p_cam[..., -1] > Camera.eps)
        s = self.scale[:, None, None]
        r = ((p2d - self.p2d) / s).masked_fill(~valid[..., None], 0.0)
        J = Pose.J_left(J_cam, p_cam) / s[..., None]
        return r, J.masked_fill(~valid[..., None, None], 0.0), valid

    def chi2(self, T: Pose) -> Tensor:
        """(B,) sum of the squared normalised residuals at T (no robust loss): the keypoints'
        chi-square, whose rise from the PnP pose's measures how far T left what they support."""
        r, _, _ = self.residuals(T)
        return (r ** 2).sum((-1, -2))

    def system(self, T: Pose) -> Tuple[Tensor, Tensor]:
        """The term's gradient (B, 6) and Gauss-Newton Hessian (B, 6, 6) at T (IRLS of the Cauchy
        loss), times ``weight``."""
        r, J, valid = self.residuals(T)
        sq = (r ** 2).sum(-1)
        w = (valid.to(sq.dtype) / (1 + sq / CAUCHY ** 2)) * self.weight[:, None]
        Jw = J * w[..., None, None]
        g = (Jw.transpose(-1, -2) @ r[..., None])[..., 0].sum(1)
        H = (Jw.transpose(-1, -2) @ J).sum(1)
        return g, H


def residual_scale(p2d_pixels, projected, floor: float = 0.5) -> float:
    """The keypoints' residual scale s_k: their root mean square reprojection error at the pose
    that projects them to ``projected``, at least ``floor`` pixels."""
    import numpy as np
    e = np.asarray(p2d_pixels, np.float64) - np.asarray(projected, np.float64)
    return float(max(np.sqrt(np.mean((e ** 2).sum(-1))) if len(e) else floor, floor))


def scaled_system(lambda_f: Optional[Tensor], g: Tensor, H: Tensor, keypoints: Optional[KeypointTerm], T: Pose,
                  spread: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """The LM's system with the keypoint term added: ``g + k g_k``, ``H + k H_k`` with k = s_f^2, the
    featuremetric residuals' scale (``spread``; fixed at the level's start: ``lambda_f``, returned)."""
    if keypoints is None:
        return g, H, lambda_f
    if lambda_f is None:
        lambda_f = spread.clamp(min=1e-12).detach()
    g_k, H_k = keypoints.system(T)
    return g + lambda_f[:, None] * g_k.to(g), H + lambda_f[:, None, None] * H_k.to(H), lambda_f
