import pytest
import torch

from pixloc.interpolation import Interpolator, append_gradient_maps, can_reduce_taps, reduce_taps


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


@pytest.mark.parametrize("shape", [(2, 9, 7, 11), (3, 17, 40, 64), (1, 5, 2, 3)])
def test_reduced_taps_give_the_products_of_the_official_samples(shape):
    """``reduce_taps`` (the LM at inference on CPU) gives |r|^2, J_f^T r and J_f^T J_f of the official
    5 taps and the values of the channels after C, without sampling: inside, on the border, outside,
    far outside and on tiny maps (zeros outside the map on both sides)."""
    b, k, h, w = shape
    g = torch.Generator().manual_seed(k)
    maps = torch.randn(shape, generator=g, dtype=torch.float64).contiguous(memory_format=torch.channels_last)
    p = torch.rand(b, 300, 2, generator=g, dtype=torch.float64) * torch.tensor([w + 8.0, h + 8.0]) - 4
    p[0, :4] = torch.tensor([[0.0, 0.0], [w - 1.0, h - 1.0], [1e9, -1e9], [-1.5, h - 0.5]], dtype=torch.float64)
    p[0, 4:10] = torch.randint(0, min(h, w), (6, 2), generator=g).to(p)  # on cells' centres
    F = torch.randn(b, 300, k - 1, generator=g, dtype=torch.float64)
    assert can_reduce_taps(maps) and not can_reduce_taps(maps.contiguous())
    sq, Jf_r, Jf_Jf, rest = reduce_taps(maps, p, F)
    values, _, grads = Interpolator("linear", pad=0)(maps, p, gradients=True)
    r, J = values[..., :-1] - F, grads[..., :-1, :]
    for got, want in ((sq, (r * r).sum(-1)), (Jf_r, (J * r[..., None]).sum(-2)),
                      (Jf_Jf, J.transpose(-1, -2) @ J), (rest, values[..., -1:])):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    p[0, 0] = float("nan")  # zeros, as grid_sample gives
    assert all(torch.isfinite(x).all() for x in reduce_taps(maps, p, F))


def test_reduced_taps_read_only_the_cells_of_their_taps():
    """A map decoded only where it is read (``pipeline.localization.finest``) holds garbage elsewhere:
    ``reduce_taps`` reads only the cells inside the map that the official taps read, so points far
    outside or at non-finite coordinates give zeros, and points near the border their taps' figures."""
    g = torch.Generator().manual_seed(3)
    clean = torch.randn(1, 9, 40, 60, generator=g, dtype=torch.float64)
    p = torch.tensor([[[30.3, 20.7], [-1e6, 5.0], [float("nan"), 3.0], [float("inf"), float("-inf")],
                       [-0.4, 10.2], [59.5, 39.2], [-2.5, -2.5], [62.9, 20.0]]], dtype=torch.float64)
    decoded = torch.zeros(40, 60, dtype=torch.bool)  # the taps' cells of the points near the map
    for x, y in p[0, [0, 4, 5, 6, 7]].floor().long().tolist():
        decoded[max(y - 1, 0):max(y + 3, 0), max(x - 1, 0):max(x + 3, 0)] = True
    maps = clean.masked_fill(~decoded, float("nan")).contiguous(memory_format=torch.channels_last)
    F = torch.randn(1, 8, 8, generator=g, dtype=torch.float64)
    sq, Jf_r, Jf_Jf, rest = reduce_taps(maps, p, F)
    values, _, grads = Interpolator("linear", pad=0)(clean, torch.nan_to_num(p, nan=-1e9), gradients=True)
    r, J = values[..., :-1] - F, grads[..., :-1, :]
    torch.testing.assert_close(sq, (r * r).sum(-1), rtol=0, atol=1e-12)
    torch.testing.assert_close(Jf_r, (J * r[..., None]).sum(-2), rtol=0, atol=1e-12)
    torch.testing.assert_close(Jf_Jf, J.transpose(-1, -2) @ J, rtol=0, atol=1e-12)
    torch.testing.assert_close(rest, values[..., -1:], rtol=0, atol=1e-12)
    assert (Jf_Jf[0, 1:4] == 0).all() and (Jf_r[0, 1:4] == 0).all()  # far outside: zero samples
    torch.testing.assert_close(sq[0, 1:4], (F[0, 1:4] ** 2).sum(-1), rtol=0, atol=1e-12)


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
