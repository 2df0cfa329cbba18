"""Problems that move as one body: the cameras of a rig at one instant, or the frames of a sequence chunk.

Problem b's camera pose is ``cam_from_body[b] @ body_from_world[index[b]]``: the LM optimises the
body's pose, and each camera's residuals reach it through the chain rule. With the solver's left
update of a camera pose, ``T <- from_aa(w, t) @ T`` (translation first), a left update of the body
moves camera b by the adjoint of its ``cam_from_body`` = (R, t):

    delta_cam = A delta_body,   A = [[R, [t]x R], [0, R]],

so a camera's gradient g and Gauss-Newton Hessian H (of its own residuals) become A^T g and
A^T H A, summed over the body's cameras: the same normal equations, one more transform in the chain
(``reduce``). A camera whose points all leave its image adds nothing; the body fails only when all its
cameras together have fewer valid points than the solver needs.
"""

from dataclasses import dataclass
from functools import cached_property
from typing import Tuple

import torch
from torch import Tensor

from ..geometry import Pose, lie


@dataclass(frozen=True)
class Bodies:
    """index: (B,) long, the body of each problem, every body 0..K-1 with at least one problem;
    cam_from_body: (B,) each problem's camera pose in its body's frame."""

    index: Tensor
    cam_from_body: Pose

    def __post_init__(self):
        if self.index.dim() != 1 or self.index.dtype != torch.long:
            raise ValueError(f"Bodies: index must be (B,) long, got {tuple(self.index.shape)} {self.index.dtype}.")
        if tuple(self.cam_from_body.shape) != tuple(self.index.shape):
            raise ValueError(f"Bodies: cam_from_body must be (B,) = {tuple(self.index.shape)}, "
                             f"got {tuple(self.cam_from_body.shape)}.")
        if len(self.index) and (int(self.index.min()) < 0 or
                                not bool(torch.bincount(self.index).gt(0).all())):
            raise ValueError("Bodies: the body indices must be 0..K-1, each with at least one problem.")

    @classmethod
    def of(cls, keys, cam_from_body: Pose) -> "Bodies":
        """Bodies from one hashable key per problem (problems of one key are one body, numbered in
        order of first appearance)."""
        number = {}
        index = torch.tensor([number.setdefault(k, len(number)) for k in keys], dtype=torch.long)
        return cls(index, cam_from_body)

    @property
    def num_bodies(self) -> int:
        return int(self.index.max()) + 1 if len(self.index) else 0

    @cached_property
    def first(self) -> Tensor:
        """(K,) the first problem of each body."""
        B = len(self.index)
        order = torch.arange(B - 1, -1, -1)
        return torch.empty(self.num_bodies, dtype=torch.long).scatter_(0, self.index.flip(0), order)

    @cached_property
    def adjoint(self) -> Tensor:
        """(B, 6, 6) A of each problem: delta_cam = A delta_body."""
        R, t = self.cam_from_body.R, self.cam_from_body.t
        A = R.new_zeros(R.shape[:-2] + (6, 6))
        A[..., :3, :3] = R
        A[..., :3, 3:] = lie.skew(t) @ R
        A[..., 3:, 3:] = R
        return A

    def to(self, device) -> "Bodies":
        return Bodies(self.index.to(device), self.cam_from_body.to(device))

    def body_poses(self, cam_from_world: Pose) -> Pose:
        """(K,) body_from_world from each body's first problem's camera pose."""
        first = self.first.to(cam_from_world.device)
        return self.cam_from_body.to(cam_from_world.data)[first].inv() @ cam_from_world[first]

    def camera_poses(self, body_from_world: Pose) -> Pose:
        """(B,) cam_from_world of each problem."""
        return self.cam_from_body.to(body_from_world.data) @ body_from_world[self.index.to(body_from_world.device)]

    def reduce(self, g: Tensor, H: Tensor) -> Tuple[Tensor, Tensor]:
        """Per problem (B, 6) and (B, 6, 6) in its camera's update -> per body (K, 6) and (K, 6, 6)."""
        A = self.adjoint.to(g)
        At = A.transpose(-1, -2)
        index = self.index.to(g.device)
        g_b = (At @ g[..., None])[..., 0]
        H_b = At @ H @ A
        K = self.num_bodies
        return (g.new_zeros(K, 6).index_add_(0, index, g_b), H.new_zeros(K, 6, 6).index_add_(0, index, H_b))

    def sum(self, x: Tensor) -> Tensor:
        """(B,) per problem -> (K,) summed per body."""
        return x.new_zeros(self.num_bodies).index_add_(0, self.index.to(x.device), x)

    def spread(self, x: Tensor) -> Tensor:
        """(K, ...) per body -> (B, ...) per problem."""
        return x[self.index.to(x.device)]
