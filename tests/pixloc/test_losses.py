import pytest
import torch

from pixloc.losses import get_loss


@pytest.mark.parametrize("spec", ["squared_loss", "scaled_barron(0, 0.1)", "scaled_barron(1, 2)",
                                  "barron(-2, 0.5)", "huber(0.3)", "cauchy(0.2)"])
def test_first_derivative_matches_autograd(spec):
    x = torch.linspace(1e-3, 3, 50, dtype=torch.float64, requires_grad=True)
    rho, d1, _ = get_loss(spec)(x)
    (g,) = torch.autograd.grad(rho.sum(), x)
    torch.testing.assert_close(d1, g)


def test_official_default_weight():
    x = torch.tensor([0.0, 0.01, 0.1, 1.0])
    _, w, _ = get_loss("scaled_barron(0, 0.1)")(x)
    torch.testing.assert_close(w, 1 / (1 + 50 * x))


def test_unknown_loss_is_named():
    with pytest.raises(ValueError, match="Unknown robust loss 'tukey"):
        get_loss("tukey(1)")
    with pytest.raises(ValueError, match="Bad arguments"):
        get_loss("scaled_barron(1)")
