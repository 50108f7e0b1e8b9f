"""The one noise protocol (retinexgs/data/noise_model.py): a raw scene's RawNoise and a photo scene's CaptureNoise are
both Poisson–Gaussian models with per-channel a, b, whose variance is a·y + b (clamped at 0)."""
import numpy as np
import pytest

from retinexgs.data.noise_model import PoissonGaussian, is_noise_model
from retinexgs.data.raw_noise import RawNoise
from retinexgs.train.noise import CaptureNoise

A, B = (1e-3, 2e-3, 3e-3), (1e-5, 2e-5, -4e-3)


@pytest.mark.parametrize("model", [RawNoise(A, B, "profile"),
                                   CaptureNoise(A, B, gains=(1.0,), sigma=(0.01,), views=3)])
def test_both_noise_models_follow_the_protocol(model):
    assert isinstance(model, PoissonGaussian) and is_noise_model(model)
    y = np.array([[0.0, 0.5, 1.0], [0.2, 0.2, 0.2]])
    want = np.maximum(np.array(A) * y + np.array(B), 0.0)
    np.testing.assert_allclose(model.variance(y), want)
    np.testing.assert_allclose(model.variance(0.5), np.maximum(np.array(A) * 0.5 + np.array(B), 0.0))
    assert model.variance(0.0)[2] == 0.0  # the blue channel's negative offset clamps at black
    np.testing.assert_allclose(model.std(y), np.sqrt(want))
    assert isinstance(model.describe(), str) and model.describe()


def test_something_else_is_not_a_noise_model():
    assert not is_noise_model(object()) and not is_noise_model((A, B))
