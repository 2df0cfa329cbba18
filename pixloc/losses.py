"""Robust losses on squared residual norms x = |r|^2.

Every loss returns ``(rho(x), rho'(x), rho''(x))``; the solver weights each
residual by rho'(x) (iteratively reweighted least squares).
"""

import re
from typing import Callable, Tuple

import torch
from torch import Tensor

RobustLoss = Callable[[Tensor], Tuple[Tensor, Tensor, Tensor]]


def squared(x: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Plain least squares."""
    return x, torch.ones_like(x), torch.zeros_like(x)


def barron(x: Tensor, alpha: float) -> Tuple[Tensor, Tensor, Tensor]:
    """Barron's general robust loss at scale 1 (CVPR 2019), on squared inputs.

    alpha = 2: L2; 0: Cauchy/log; 1: pseudo-Huber (Charbonnier); -2: Geman-McClure.
    The second derivative is not needed by the solver and returned as zeros,
    as in official PixLoc.
    """
    zeros = torch.zeros_like(x)
    if alpha == 2:
        return x, torch.ones_like(x), zeros
    if alpha == 0:
        return 2 * torch.log1p(torch.clamp(0.5 * x, max=33e37)), 2 / (x + 2), zeros
    beta = max(abs(alpha - 2.0), 1e-7)
    a = alpha if abs(alpha) > 1e-7 else 1e-7
    base = x / beta + 1
    return 2 * (beta / a) * (base ** (0.5 * alpha) - 1), base ** (0.5 * alpha - 1), zeros


def huber(x: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Huber loss at scale 1, on squared inputs: x below 1, 2 sqrt(x) - 1 above."""
    inlier = x <= 1
    sx = x.clamp(min=torch.finfo(x.dtype).tiny).sqrt()
    loss = torch.where(inlier, x, 2 * sx - 1)
    d1 = torch.where(inlier, torch.ones_like(x), 1 / sx)
    d2 = torch.where(inlier, torch.zeros_like(x), -1 / (2 * x.clamp(min=1e-12) * sx))
    return loss, d1, d2


def scaled(loss: Callable[[Tensor], Tuple[Tensor, Tensor, Tensor]], c: float) -> RobustLoss:
    """Loss with scale c: c^2 rho(x / c^2); the first derivative keeps its value."""
    c2 = c * c

    def fn(x: Tensor):
        rho, d1, d2 = loss(x / c2)
        return rho * c2, d1, d2 / c2
    return fn


def scaled_barron(alpha: float, c: float) -> RobustLoss:
    """Official PixLoc's default is ``scaled_barron(0, 0.1)``: weight 1 / (1 + 50 x)."""
    return scaled(lambda x: barron(x, alpha), c)


def cauchy(c: float) -> RobustLoss:
    """Cauchy loss with scale c (Barron alpha = 0)."""
    return scaled_barron(0.0, c)


def scaled_huber(c: float) -> RobustLoss:
    return scaled(huber, c)


_FACTORIES = {
    "squared_loss": lambda: squared,
    "squared": lambda: squared,
    "huber_loss": lambda: huber,
    "huber": lambda c=1.0: scaled_huber(c),
    "cauchy": lambda c=1.0: cauchy(c),
    "scaled_barron": scaled_barron,
    "barron": lambda alpha, c=1.0: scaled_barron(alpha, c),
}
_CALL = re.compile(r"^\s*([a-z_]+)\s*(?:\((.*)\))?\s*$")


def get_loss(spec: str) -> RobustLoss:
    """A loss from its name, e.g. ``"scaled_barron(0, 0.1)"`` or ``"huber(0.5)"``.

    Parses official PixLoc config strings without ``eval``.
    """
    m = _CALL.match(spec)
    if m is None or m.group(1) not in _FACTORIES:
        raise ValueError(f"Unknown robust loss {spec!r}; known: {sorted(_FACTORIES)}.")
    args = [float(a) for a in m.group(2).split(",")] if m.group(2) and m.group(2).strip() else []
    try:
        return _FACTORIES[m.group(1)](*args)
    except TypeError as e:
        raise ValueError(f"Bad arguments for robust loss {spec!r}: {e}") from None
