"""retinex.denoise.pilot_wiener: a noisy view filtered with Wiener gains from a cleaner pilot (issue 64 item 1)."""
import pytest
import torch

from retinexgs.errors import UserError
from retinexgs.retinex.denoise import NoiseModel, pilot_wiener

NOISE = NoiseModel(a=(0.004, 0.004, 0.004), b=(1e-4, 1e-4, 1e-4))


def scene(h=48, w=64, seed=0):
    """A clean linear image (smooth colour gradients and a few edges) and a Poisson-Gaussian noisy copy of it."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    clean = torch.stack([0.05 + 0.1 * xx, 0.08 + 0.05 * yy, 0.04 + 0.06 * (xx > 0.5)], -1).double()
    var = NOISE.a[0] * clean + NOISE.b[0]
    noisy = clean + var.sqrt() * torch.randn(clean.shape, generator=g, dtype=torch.float64)
    return clean, noisy


def mse(a, b):
    return float(((a - b) ** 2).mean())


def test_a_clean_pilot_removes_most_of_the_noise_and_keeps_the_light():
    clean, noisy = scene()
    out = pilot_wiener(noisy, clean, NOISE)
    assert out.shape == noisy.shape and out.dtype == noisy.dtype
    assert mse(out, clean) < 0.1 * mse(noisy, clean)
    # unbiased: the mean light is kept (the GAT's exact inverse of the expectation, not the algebraic one)
    assert abs(float(out.mean() - clean.mean())) < 0.02 * float(clean.mean())


def test_the_gain_follows_the_pilot():
    """A pilot that is the noisy view itself keeps most of it (every coefficient above the noise passes); a clean
    pilot keeps less of the view and lands nearer the light."""
    clean, noisy = scene(seed=1)
    self_piloted = pilot_wiener(noisy, noisy, NOISE)
    assert mse(self_piloted, clean) < mse(noisy, clean)
    assert mse(self_piloted, noisy) < mse(pilot_wiener(noisy, clean, NOISE), noisy)
    assert mse(pilot_wiener(noisy, clean, NOISE), clean) < mse(self_piloted, clean)


@pytest.mark.parametrize("shape", [(48, 64), (37, 29), (5, 3)])
def test_any_size_and_float32(shape):
    clean, noisy = scene(*shape)
    out = pilot_wiener(noisy.float(), clean.float(), NOISE)
    assert out.dtype == torch.float32 and out.shape == noisy.shape and torch.isfinite(out).all()
    assert mse(out.double(), clean) < mse(noisy, clean)


def test_the_chroma_of_another_estimate_is_kept():
    """``chroma``: the luma filtered with the pilot's gains, the chroma that of the estimate given (a render's colour
    blotches would pass the chroma gains). A pilot with a wrong colour cast then leaves the colour alone."""
    clean, noisy = scene(seed=2)
    tinted = clean * torch.tensor([1.6, 1.0, 0.5], dtype=torch.float64)  # same structure, a strong cast
    cast = pilot_wiener(noisy, tinted, NOISE)
    kept = pilot_wiener(noisy, tinted, NOISE, chroma=clean)
    ratio = lambda x: float(x[..., 0].mean() / x[..., 2].mean())  # noqa: E731
    assert abs(ratio(kept) - ratio(clean)) < abs(ratio(cast) - ratio(clean))
    assert abs(ratio(kept) - ratio(clean)) < 0.1 * ratio(clean)


def test_bad_inputs_are_one_line_errors():
    clean, noisy = scene()
    with pytest.raises(UserError, match="two \\[H,W,3\\] images"):
        pilot_wiener(noisy, clean[:10], NOISE)
    with pytest.raises(UserError, match="even number"):
        pilot_wiener(noisy, clean, NOISE, block=7)
    with pytest.raises(UserError, match="chroma must have the view's shape"):
        pilot_wiener(noisy, clean, NOISE, chroma=clean[:10])
