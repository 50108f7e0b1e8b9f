"""The fused SSIM kernels (csrc/include/rgs/ssim.h, CPU) against their pure-torch twin, evaluate.metrics.ssim with
"same" padding, and float64 finite differences."""
import pytest
import torch

from retinexgs.evaluate.metrics import gaussian_window, ssim
from retinexgs.render.ssim import fused_ssim_map
from retinexgs.train import losses

C1, C2 = 0.01 ** 2, 0.03 ** 2


def pair(shape, dtype=torch.float64, seed=0, grad=True):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=torch.float64).to(dtype).requires_grad_(grad)
    y = torch.rand(shape, generator=g, dtype=torch.float64).to(dtype)
    return x, y


# sizes below, at and above the window, odd and even, one plane and many
@pytest.mark.parametrize("shape", [(1, 1, 1, 1), (1, 1, 5, 3), (2, 3, 11, 11), (1, 9, 37, 29), (3, 2, 40, 17)])
@pytest.mark.parametrize("taps,sigma", [(11, 1.5), (3, 0.8), (15, 3.0), (1, 1.0)])
def test_map_and_gradient_match_the_torch_twin_float64(shape, taps, sigma):
    x, y = pair(shape)
    w = gaussian_window(taps, sigma, dtype=torch.float64)
    s = fused_ssim_map(x, y, w, C1, C2)
    r = ssim(x, y, window=taps, sigma=sigma, reduction="none")
    assert s.shape == r.shape
    torch.testing.assert_close(s, r, rtol=0, atol=1e-12)
    g = torch.randn(s.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    gs, = torch.autograd.grad((s * g).sum(), x)
    gr, = torch.autograd.grad((r * g).sum(), x)
    torch.testing.assert_close(gs, gr, rtol=1e-10, atol=1e-12)


def test_float32_matches_the_twin():
    x, y = pair((1, 9, 72, 96), torch.float32)
    w = gaussian_window(11, 1.5, dtype=torch.float64)
    s = fused_ssim_map(x, y, w, C1, C2)
    r = ssim(x, y, reduction="none")
    torch.testing.assert_close(s, r, rtol=0, atol=2e-5)
    gs, = torch.autograd.grad(s.mean(), x)
    gr, = torch.autograd.grad(r.mean(), x)
    torch.testing.assert_close(gs, gr, rtol=1e-3, atol=1e-8)


@pytest.mark.parametrize("shape,taps", [((1, 2, 9, 13), 5), ((2, 1, 4, 6), 11), ((1, 1, 16, 3), 7)])
def test_gradient_matches_finite_differences(shape, taps):
    x, y = pair(shape, seed=3)
    w = gaussian_window(taps, 1.2, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: fused_ssim_map(a, y, w, C1, C2), (x,), eps=1e-6, atol=1e-7)


def test_equal_images_score_one_and_a_changed_pixel_lowers_its_neighbourhood():
    x, _ = pair((1, 1, 20, 20), grad=False)
    w = gaussian_window(11, 1.5, dtype=torch.float64)
    torch.testing.assert_close(fused_ssim_map(x, x, w, C1, C2), torch.ones_like(x), rtol=0, atol=1e-12)
    y = x.clone()
    y[0, 0, 10, 10] += 0.5
    s = fused_ssim_map(x, y, w, C1, C2)
    assert s[0, 0, 10, 10] < 0.99 and float(s[0, 0, 0, 0]) == pytest.approx(1.0, abs=1e-12)


def test_any_leading_shape_is_planes():
    x, y = pair((2, 3, 4, 10, 12))
    w = gaussian_window(5, 1.0, dtype=torch.float64)
    s = fused_ssim_map(x, y, w, C1, C2)
    r = ssim(x.reshape(1, 24, 10, 12), y.reshape(1, 24, 10, 12), window=5, sigma=1.0, reduction="none")
    torch.testing.assert_close(s.reshape(r.shape), r, rtol=0, atol=1e-12)


def test_no_partials_without_a_gradient():
    x, y = pair((1, 3, 20, 20), grad=False)
    with torch.no_grad():
        s = fused_ssim_map(x, y, gaussian_window(11, 1.5, dtype=torch.float64), C1, C2)
    torch.testing.assert_close(s, ssim(x, y, reduction="none"), rtol=0, atol=1e-12)


def test_bad_arguments_are_one_line_errors():
    x, y = pair((1, 3, 8, 8))
    w = gaussian_window(11, 1.5, dtype=torch.float64)
    with pytest.raises(ValueError, match="odd number of taps"):
        fused_ssim_map(x, y, gaussian_window(17, 2.0, dtype=torch.float64), C1, C2)
    with pytest.raises(ValueError, match="odd number of taps"):
        fused_ssim_map(x, y, torch.ones(4, dtype=torch.float64) / 4, C1, C2)
    with pytest.raises(ValueError, match="shape"):
        fused_ssim_map(x, y[..., :7], w, C1, C2)
    with pytest.raises(TypeError, match="dtype"):
        fused_ssim_map(x, y.float(), w, C1, C2)
    with pytest.raises(ValueError, match="y requires a gradient"):
        fused_ssim_map(x, y.requires_grad_(), w, C1, C2)


def test_the_training_losses_use_it_and_keep_their_values():
    """losses.ssim_map (every training SSIM) takes the fused path for a target and the twin where y needs a
    gradient, with the same values either way."""
    x, y = pair((1, 9, 24, 31))
    fused = losses.ssim_map(x, y)
    assert fused.grad_fn is not None and "FusedSSIM" in type(fused.grad_fn).__name__
    twin = losses.ssim_map(x, y.clone().requires_grad_())
    assert "FusedSSIM" not in type(twin.grad_fn).__name__
    torch.testing.assert_close(fused, twin, rtol=0, atol=1e-12)
    total, _ = losses.supervision_loss(x[:, :3], x[:, 3:6], y[:, :3], y[:, 3:6], y[:, 6:9])
    R, L = x[:, :3].detach().requires_grad_(), x[:, 3:6].detach().requires_grad_()
    by_hand = 0.5 * (0.8 * (R - y[:, :3]).abs().mean() + 0.2 * (1 - ssim(R, y[:, :3])))
    by_hand = by_hand + 0.5 * (0.8 * (L - y[:, 3:6]).abs().mean() + 0.2 * (1 - ssim(L, y[:, 3:6])))
    by_hand = by_hand + 0.8 * (R * L - y[:, 6:9]).abs().mean() + 0.2 * (1 - ssim(R * L, y[:, 6:9]))
    torch.testing.assert_close(total, by_hand, rtol=1e-12, atol=1e-12)
