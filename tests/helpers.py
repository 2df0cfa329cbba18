"""Helpers shared by the tests."""

import torch


def jacobian(fn, x: torch.Tensor) -> torch.Tensor:
    """Autograd Jacobian of fn at x, for fn: (..., N, D) -> (..., N, E), batched per row.

    Returns (..., N, E, D): each output row depends only on its input row.
    """
    x = x.detach().clone().requires_grad_(True)
    y = fn(x)
    rows = []
    for e in range(y.shape[-1]):
        (g,) = torch.autograd.grad(y[..., e].sum(), x, retain_graph=True)
        rows.append(g)
    return torch.stack(rows, -2)


BATCH_SHAPES = [(), (1,), (5,)]
