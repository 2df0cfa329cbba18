"""Damping of the Levenberg-Marquardt step, one 6-vector (dt, dw) per problem."""

from typing import Sequence, Tuple

import torch
from torch import Tensor, nn


class ConstantDamping(nn.Module):
    """A fixed damping vector lambda (6,), translation first."""

    def __init__(self, lambda_: Sequence[float] | float = 0.0):
        super().__init__()
        lam = torch.as_tensor(lambda_, dtype=torch.float32).expand(6).clone()
        if (lam < 0).any():
            raise ValueError(f"Damping must be non-negative, got {lam.tolist()}.")
        self.register_buffer("lambda_", lam)

    def forward(self) -> Tensor:
        return self.lambda_


class LearnedDamping(nn.Module):
    """Official PixLoc's learned constant damping: lambda = 10^(lo + sigmoid(theta) (hi - lo)).

    theta (6,) starts at 0, i.e. lambda = 10^-0.5 for the default range [-6, 5].
    Official checkpoints store it as ``optimizer.{level}.dampingnet.const``.
    """

    def __init__(self, log_range: Tuple[float, float] = (-6.0, 5.0)):
        super().__init__()
        self.log_range = tuple(log_range)
        self.theta = nn.Parameter(torch.zeros(6))

    def forward(self) -> Tensor:
        lo, hi = self.log_range
        return 10.0 ** (lo + self.theta.sigmoid() * (hi - lo))
