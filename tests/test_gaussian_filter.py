"""SSIM's Gaussian filter (retinexgs.evaluate.metrics.gaussian_filter): two 1-D passes must equal the 2-D depthwise
convolution with the outer-product window, in values and gradients, for both paddings; the SSIMs built on it
(training's and evaluation's) must not move."""
import pytest
import torch
import torch.nn.functional as F

from retinexgs.evaluate import metrics as M
from retinexgs.train import losses as Lo


pytestmark = pytest.mark.usefixtures("one_thread")

# The CUDA path (depthwise convolutions in float64 too) where this machine has a GPU; the CPU's in any case.
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
# What "the same" means: float32 sums of 11 x 11 products in another order; float64 to rounding.
TOL = {torch.float32: 1e-6, torch.float64: 1e-12}


def filter_2d(x: torch.Tensor, size: int, sigma: float, pad: int) -> torch.Tensor:
    """The reference: one depthwise conv2d with the [size, size] outer product of the 1-D window."""
    g = M.gaussian_window(size, sigma, torch.float64)
    w = torch.outer(g, g).to(x.dtype).to(x.device).expand(x.shape[1], 1, size, size)
    return F.conv2d(x, w, padding=pad, groups=x.shape[1])


def _rand(*shape, dtype=torch.float64, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(*shape, generator=g, dtype=torch.float64).to(dtype=dtype, device=device)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size,sigma", [(3, 0.8), (7, 1.0), (11, 1.5)])
@pytest.mark.parametrize("padding", ["same", "valid"])
def test_two_1d_passes_equal_the_2d_filter(device, dtype, size, sigma, padding):
    pad = size // 2 if padding == "same" else 0
    x = _rand(3, 5, 23, 31, dtype=dtype, device=device).requires_grad_(True)  # batch > 1, non-square
    out = M.gaussian_filter(x, size, sigma, pad)
    ref = filter_2d(x, size, sigma, pad)
    assert out.shape == ref.shape == (3, 5, 23 - 2 * (size // 2 - pad), 31 - 2 * (size // 2 - pad))
    torch.testing.assert_close(out, ref, rtol=0, atol=TOL[dtype])
    g = _rand(*ref.shape, dtype=dtype, device=device, seed=1)
    (ga,) = torch.autograd.grad(out, x, g)
    (gb,) = torch.autograd.grad(ref, x, g)
    torch.testing.assert_close(ga, gb, rtol=0, atol=TOL[dtype] * size)  # a gradient sums size^2 more terms


@pytest.mark.parametrize("device", DEVICES)
def test_the_filter_is_not_the_identity_or_a_box(device):
    """A centred impulse comes out as the window's outer product (guards the reference itself)."""
    x = torch.zeros(1, 1, 11, 11, dtype=torch.float64, device=device)
    x[..., 5, 5] = 1.0
    g = M.gaussian_window(11, 1.5, torch.float64)
    torch.testing.assert_close(M.gaussian_filter(x, 11, 1.5, 5)[0, 0].cpu(), torch.outer(g, g), rtol=0, atol=1e-15)


@pytest.mark.parametrize("padding,window,sigma", [("same", 5, 1.0), ("valid", 11, 1.5), ("same", 11, 1.5)])
def test_ssim_gradcheck_float64_through_the_filter(padding, window, sigma):
    x = _rand(2, 2, 12, 13, seed=2).requires_grad_(True)
    y = _rand(2, 2, 12, 13, seed=3).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: M.ssim(a, b, window=window, sigma=sigma, padding=padding),
                                    (x, y), eps=1e-6, atol=1e-8)


def test_evaluation_ssim_is_unchanged_against_the_2d_filter(monkeypatch):
    rng = torch.Generator().manual_seed(4)
    truth = torch.rand(40, 52, 3, generator=rng, dtype=torch.float64)
    out = (truth + 0.1 * torch.randn(40, 52, 3, generator=rng, dtype=torch.float64)).clamp(0, 1)
    ours = M.ssim_metric(out, truth)
    monkeypatch.setattr(M, "gaussian_filter", filter_2d)
    ref = M.ssim_metric(out, truth)
    assert 0.1 < ref < 0.99
    assert ours == pytest.approx(ref, abs=1e-12)


@pytest.mark.parametrize("device", DEVICES)
def test_training_ssim_is_unchanged_against_the_2d_filter(monkeypatch, device):
    """The training loss's SSIM (float32, "same"), its map and its gradient."""
    x = _rand(1, 3, 36, 48, dtype=torch.float32, device=device, seed=5).requires_grad_(True)
    y = _rand(1, 3, 36, 48, dtype=torch.float32, device=device, seed=6)

    def run():
        s = Lo.ssim(x, y, padding="same", reduction="none")
        (g,) = torch.autograd.grad(s.mean(), x)
        return s.detach(), g

    ours = run()
    monkeypatch.setattr(M, "gaussian_filter", filter_2d)
    ref = run()
    # Per pixel, float32 rounding of the moments is amplified by SSIM's quotient where the variances are small.
    torch.testing.assert_close(ours[0], ref[0], rtol=0, atol=1e-5)
    assert float(ours[0].mean()) == pytest.approx(float(ref[0].mean()), abs=1e-6)
    torch.testing.assert_close(ours[1], ref[1], rtol=0, atol=1e-8)
