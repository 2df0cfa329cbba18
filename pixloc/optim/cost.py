"""The featuremetric residual of PixLoc and its Jacobian w.r.t. the query pose."""

from dataclasses import dataclass, replace
from functools import cached_property
from typing import NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from ..geometry import Camera, Pose
from ..interpolation import Interpolator, append_gradient_maps


@dataclass(frozen=True)
class FeaturemetricProblem:
    """A batch of B independent alignment problems: find cam_from_world of the query.

    p3d_world: (B, N, 3) 3D points in the world frame.
    F_ref: (B, N, C) reference features of the points, used as given.
    F_query: (B, C, H, W) dense query features at this level, used as given
        (official PixLoc L2-normalises the dense map, not the samples).
    camera: (B,) query camera at the resolution of ``F_query``.
    W_ref: (B, N) reference confidences, or None.
    W_query: (B, H, W) dense query confidences, or None. Both or neither.
    mask: (B, N) bool, observations to use (padding of ragged batches), or None.
    maps: (B, C + 1, H, W), F_query and W_query stacked, when the caller has built them so
        (``new_query_maps``): F_query and W_query are then views of it, and the largest
        tensor of the problem is not copied again.
    """

    p3d_world: Tensor
    F_ref: Tensor
    F_query: Tensor
    camera: Camera
    W_ref: Optional[Tensor] = None
    W_query: Optional[Tensor] = None
    mask: Optional[Tensor] = None
    maps: Optional[Tensor] = None

    def __post_init__(self):
        p, F, Fq = self.p3d_world, self.F_ref, self.F_query
        if p.dim() != 3 or p.shape[-1] != 3:
            raise ValueError(f"p3d_world must be (B, N, 3), got {tuple(p.shape)}.")
        B, N = p.shape[:2]
        if F.shape[:2] != (B, N) or F.dim() != 3:
            raise ValueError(f"F_ref must be (B, N, C) = ({B}, {N}, C), got {tuple(F.shape)}.")
        if Fq.dim() != 4 or Fq.shape[:2] != (B, F.shape[-1]):
            raise ValueError(f"F_query must be (B, C, H, W) with B={B}, C={F.shape[-1]}, got {tuple(Fq.shape)}.")
        if tuple(self.camera.shape) != (B,):
            raise ValueError(f"camera must have batch shape ({B},), got {tuple(self.camera.shape)}.")
        if (self.W_ref is None) != (self.W_query is None):
            raise ValueError("Give both W_ref and W_query confidences, or neither.")
        if self.W_ref is not None:
            if tuple(self.W_ref.shape) != (B, N):
                raise ValueError(f"W_ref must be (B, N) = ({B}, {N}), got {tuple(self.W_ref.shape)}.")
            if tuple(self.W_query.shape) != (B,) + tuple(Fq.shape[-2:]):
                raise ValueError(f"W_query must be (B, H, W) = ({B}, {Fq.shape[-2]}, {Fq.shape[-1]}), "
                                 f"got {tuple(self.W_query.shape)}.")
        if self.maps is not None and not (self.W_query is not None and self.maps.shape[1] == Fq.shape[1] + 1
                                          and torch.equal(self.maps[:, -1], self.W_query)):
            raise ValueError("maps must be F_query and W_query stacked, (B, C + 1, H, W).")
        if self.mask is not None and tuple(self.mask.shape) != (B, N):
            raise ValueError(f"mask must be (B, N) = ({B}, {N}), got {tuple(self.mask.shape)}.")
        if not torch.isfinite(p).all():
            raise ValueError("p3d_world contains NaN or infinite coordinates.")

    @classmethod
    def single(cls, p3d_world, F_ref, F_query, camera, W_ref=None, W_query=None, mask=None):
        """One problem without a batch dim: p3d (N, 3), F_ref (N, C), F_query (C, H, W), W_query (H, W)."""
        def add(x):
            return None if x is None else x[None]
        return cls(p3d_world[None], F_ref[None], F_query[None], camera.reshape(1),
                   add(W_ref), add(W_query), add(mask))

    @cached_property
    def query_maps(self) -> Tensor:
        """(B, C[+1], H, W) query features with the confidence appended as a channel,
        so that one sampling call serves both (official inference does the same).

        Laid out as ``query_maps_layout`` says."""
        if self.maps is not None:
            return self.maps
        if self.W_query is None:
            return self.F_query.contiguous(memory_format=query_maps_layout(self.F_query))
        out = new_query_maps(self.F_query.shape, self.F_query, with_confidence=True)
        C = self.F_query.shape[1]
        out[:, :C] = self.F_query
        out[:, C] = self.W_query
        return out

    @cached_property
    def query_maps_with_gradients(self) -> Tensor:
        """``query_maps`` with the central differences of the C feature channels appended (x, then
        y): (B, 3 C [+ 1], H, W), built once per problem, sampled at every LM iteration."""
        C = self.F_query.shape[1]
        maps = self.query_maps
        return append_gradient_maps(maps, C, query_maps_layout(maps, maps.shape[1] + 2 * C))

    @property
    def batch_size(self) -> int:
        return self.p3d_world.shape[0]

    def index(self, i) -> "FeaturemetricProblem":
        """Sub-batch ``i`` (an int keeps a batch of one)."""
        i = [i] if isinstance(i, int) else i

        def sel(x):
            return None if x is None else x[i]
        return replace(self, p3d_world=self.p3d_world[i], F_ref=self.F_ref[i], F_query=self.F_query[i],
                       camera=self.camera[i], W_ref=sel(self.W_ref), W_query=sel(self.W_query),
                       mask=sel(self.mask), maps=sel(self.maps))


def query_maps_layout(like: Tensor, channels: Optional[int] = None) -> torch.memory_format:
    """Memory layout of query maps for sampling. On CPU, maps of 64 channels or more are
    channels-last: bilinear sampling then reads each tap's channels contiguously, which made
    it 2.3x faster on the 129 x 175 x 256 maps of a 1024 px query (bitwise the same samples).
    Thinner maps stay as they are, unless they already are channels-last (a network prepared
    for inference gives such maps): there the layout change costs more than it saves."""
    channels = like.shape[1] if channels is None else channels
    if like.device.type == "cpu" and (channels >= 64 or _is_channels_last(like)):
        return torch.channels_last
    return torch.contiguous_format


def _is_channels_last(x: Tensor) -> bool:
    return x.dim() == 4 and x.shape[1] > 1 and not x.is_contiguous() \
        and x.is_contiguous(memory_format=torch.channels_last)


def new_query_maps(shape, like: Tensor, with_confidence: bool = True) -> Tensor:
    """An empty (B, C [+ 1], H, W) buffer for query maps, in ``query_maps_layout``."""
    B, C, H, W = shape
    C = C + int(with_confidence)
    return torch.empty((B, C, H, W), dtype=like.dtype, device=like.device,
                       memory_format=query_maps_layout(like, C))


class Linearization(NamedTuple):
    """Residuals and Jacobian factors at one pose.

    res: (B, N, C); valid: (B, N); confidence: (B, N) product of both
    confidences (None without confidences); J_f: (B, N, C, 2) feature
    gradients in the query map; J_p2d_pose: (B, N, 2, 6) projection Jacobian.
    The full Jacobian is J_f @ J_p2d_pose, never formed by the solver.
    """

    res: Tensor
    valid: Tensor
    confidence: Optional[Tensor]
    J_f: Tensor
    J_p2d_pose: Tensor


# Gradient maps (``append_gradient_maps``) are built when the map has at most this many cells per
# point: building them costs about 8 C per cell and saves about 14 C per point and LM iteration
# (5 taps and a stack against 3 channel blocks), so they pay from the second iteration, and they
# take no more memory than the 5-tap samples. Fine levels with few points keep the 5 taps.
GRADIENT_MAPS_MAX_CELLS_PER_POINT = 2


def use_gradient_maps(problem: FeaturemetricProblem, interpolator: Interpolator) -> bool:
    H, W = problem.F_query.shape[-2:]
    return interpolator.gradient_maps and H * W <= GRADIENT_MAPS_MAX_CELLS_PER_POINT * problem.p3d_world.shape[1]


def linearize(cam_from_world: Pose, problem: FeaturemetricProblem,
              interpolator: Interpolator) -> Linearization:
    """Residuals r_i = F_q(pi(T P_i)) - F_ref,i and their Jacobian factors."""
    p3d_cam = cam_from_world.transform(problem.p3d_world)
    p2d, visible = problem.camera.cam2image(p3d_cam)
    C = problem.F_ref.shape[-1]
    if use_gradient_maps(problem, interpolator):  # one sampling of maps and gradient maps: the same gradients
        values, valid, J_f = interpolator.sample_with_gradients(problem.query_maps_with_gradients, p2d, C)
    else:
        values, valid, grads = interpolator(problem.query_maps, p2d, gradients=True)
        J_f = grads[..., :C, :]
    F_p2d = values[..., :C]
    valid = valid & visible
    if problem.mask is not None:
        valid = valid & problem.mask
    confidence = None
    if problem.W_ref is not None:
        confidence = (problem.W_ref * values[..., C]).masked_fill(~valid, 0.0)
    J_p2d_pose = problem.camera.J_cam2image(p3d_cam) @ cam_from_world.J_transform(p3d_cam)
    return Linearization(F_p2d - problem.F_ref, valid, confidence, J_f, J_p2d_pose)


def robust_weights(lin: Linearization, loss_fn) -> Tuple[Tensor, Tensor]:
    """Per point (B, N): the robust cost rho of its squared residual, and its weight in the normal
    equations: rho' x validity x the product of both confidences (where there are confidences)."""
    rho, w_loss, _ = loss_fn((lin.res ** 2).sum(-1))
    weights = w_loss * lin.valid
    if lin.confidence is not None:
        weights = weights * lin.confidence
    return rho, weights


def build_system(lin: Linearization, weights: Tensor):
    """Gradient g = sum w J^T r (B, 6) and Gauss-Newton Hessian H = sum w J^T J (B, 6, 6).

    J = J_f @ J_p2d_pose is factored so that the C-dim contraction happens in
    2D first: O(N C) instead of official PixLoc's O(N C 36) per-point 6x6.
    """
    J_f = lin.J_f.transpose(-1, -2)  # B x N x 2 x C, rows contiguous (see _bilinear)
    Jf_r = (J_f @ lin.res[..., None])[..., 0]  # B x N x 2
    Jf_Jf = J_f @ J_f.transpose(-1, -2)  # B x N x 2 x 2
    B = weights.shape[0]
    Jp_w = (lin.J_p2d_pose * weights[..., None, None]).reshape(B, -1, 6)  # B x 2N x 6
    g = (Jp_w * Jf_r.reshape(B, -1, 1)).sum(1)
    H = Jp_w.transpose(1, 2) @ (Jf_Jf @ lin.J_p2d_pose).reshape(B, -1, 6)
    return g, H
