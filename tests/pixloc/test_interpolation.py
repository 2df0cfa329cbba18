import pytest
import torch

from pixloc.interpolation import Interpolator, append_gradient_maps


def linear_map(C=4, H=20, W=30, dtype=torch.float64):
    """A map that is affine in x and y per channel: bilinear and bicubic are exact."""
    g = torch.Generator().manual_seed(0)
    a, b, c = (torch.randn(C, 1, 1, generator=g, dtype=dtype) for _ in range(3))
    y, x = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    return a * x + b * y + c, (a.flatten(), b.flatten(), c.flatten())


@pytest.mark.parametrize("mode", ["linear", "cubic"])
def test_exact_on_affine_maps(mode, device):
    maps, (a, b, c) = linear_map()
    maps = maps.to(device)
    p = torch.tensor([[3.3, 4.7], [10.0, 10.0], [25.9, 15.1]], dtype=torch.float64, device=device)
    values, valid, grads = Interpolator(mode, pad=2)(maps, p, gradients=True)
    expected = p[:, :1] * a.to(device) + p[:, 1:] * b.to(device) + c.to(device)
    torch.testing.assert_close(values, expected)
    torch.testing.assert_close(grads[..., 0], a.to(device).expand(3, -1))
    torch.testing.assert_close(grads[..., 1], b.to(device).expand(3, -1))
    assert valid.all()


def test_bicubic_gradients_match_autograd():
    maps = torch.randn(1, 5, 16, 16, dtype=torch.float64)
    p = (torch.rand(1, 9, 2, dtype=torch.float64) * 10 + 3)
    interp = Interpolator("cubic", pad=1)
    _, _, grads = interp(maps, p, gradients=True)
    p_ = p.clone().requires_grad_(True)
    v, _, _ = interp(maps, p_)
    J = torch.stack([torch.autograd.grad(v[..., c].sum(), p_, retain_graph=True)[0] for c in range(5)], -2)
    torch.testing.assert_close(grads, J)


def test_bilinear_gradient_is_the_official_central_difference():
    maps = torch.randn(1, 3, 12, 12, dtype=torch.float64)
    p = torch.tensor([[[5.25, 6.5]]], dtype=torch.float64)
    interp = Interpolator("linear", pad=2)
    _, _, grads = interp(maps, p, gradients=True)
    dx = torch.tensor([1.0, 0.0], dtype=torch.float64)
    fd = (interp(maps, p + dx)[0] - interp(maps, p - dx)[0]) / 2
    torch.testing.assert_close(grads[..., 0], fd)


@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last])
def test_gradient_maps_give_the_official_gradients_everywhere_in_the_map(layout):
    """Sampling precomputed central-difference maps = central differences of samples, up to the
    border (zeros outside on both sides) and on integer coordinates; values are untouched."""
    g = torch.Generator().manual_seed(1)
    maps = torch.randn(2, 5, 9, 13, generator=g, dtype=torch.float64)
    p = torch.rand(2, 400, 2, generator=g, dtype=torch.float64) * torch.tensor([12.0, 8.0], dtype=torch.float64)
    p[:, :20] = torch.randint(0, 9, (2, 20, 2), generator=g).to(p)  # on pixel centres, borders included
    p[0, 20] = torch.tensor([12.0, 8.0])  # the far corner
    interp = Interpolator("linear", pad=0)
    values, valid, grads = interp(maps, p, gradients=True)
    stacked = append_gradient_maps(maps, 4, layout)
    v2, valid2, g2 = interp.sample_with_gradients(stacked, p, 4)
    assert stacked.shape == (2, 13, 9, 13)
    torch.testing.assert_close(v2, values, rtol=0, atol=1e-12)
    torch.testing.assert_close(g2, grads[..., :4, :], rtol=0, atol=1e-12)
    assert torch.equal(valid2, valid)
    with pytest.raises(ValueError, match="linear"):
        Interpolator("cubic").sample_with_gradients(stacked, p, 4)


@pytest.mark.parametrize("mode,pad", [("linear", 0), ("linear", 2), ("cubic", 2)])
def test_margin(mode, pad):
    maps = torch.zeros(2, 10, 10)
    margin = pad + (1 if mode == "cubic" else 0)
    p = torch.tensor([[margin, margin], [9 - margin, 9 - margin], [margin - 0.01, 5], [5, 9 - margin + 0.01]])
    _, valid, _ = Interpolator(mode, pad)(maps, p)
    assert valid.tolist() == [True, True, False, False]


@pytest.mark.parametrize("shape", [(), (1,), (5,)])
def test_batch_shapes(shape):
    maps = torch.randn(*shape, 3, 8, 9)
    p = torch.rand(*shape, 4, 2) * 6 + 1
    v, valid, g = Interpolator()(maps, p, gradients=True)
    assert v.shape == shape + (4, 3) and valid.shape == shape + (4,) and g.shape == shape + (4, 3, 2)


def test_bad_input():
    with pytest.raises(ValueError, match="Unknown interpolation mode"):
        Interpolator("nearest")
    with pytest.raises(ValueError, match=r"points \(B, N, 2\)"):
        Interpolator()(torch.zeros(2, 3, 8, 8), torch.zeros(3, 4, 2))
