"""The one noise protocol of a capture's views: Poisson–Gaussian noise, ``var(y) = a·y + b`` per channel (R, G, B) of
the values training reads. A camera-raw scene's :class:`retinexgs.data.raw_noise.RawNoise` (the DNG NoiseProfile or
the mosaic's estimate) and a photo scene's :class:`retinexgs.train.noise.CaptureNoise` (measured on the photos'
flat patches) both are one: the denoiser (:mod:`retinexgs.retinex.denoise`) and the linear reconstruction's weights
read any noise model through this interface."""
from __future__ import annotations

from typing import Tuple, Union

import numpy as np

ArrayLike = Union[float, np.ndarray]


class PoissonGaussian:
    """Mixin of a noise model with per-channel ``a`` (the signal-dependent, shot-noise part) and ``b`` (the
    signal-independent, read-noise part): its variance and standard deviation at a level ``y``."""

    a: Tuple[float, float, float]
    b: Tuple[float, float, float]

    def variance(self, y: ArrayLike) -> np.ndarray:
        """[..., 3] the noise variance at level(s) ``y`` (a scalar, or [..., 3] per channel), clamped at 0 (the model
        can go negative below black, where its fit has no data)."""
        y = np.asarray(y, dtype=np.float64)
        if y.ndim == 0:
            y = np.full(3, float(y))
        return np.maximum(np.asarray(self.a) * y + np.asarray(self.b), 0.0)

    def std(self, y: ArrayLike) -> np.ndarray:
        """[..., 3] the noise standard deviation at level(s) ``y``."""
        return np.sqrt(self.variance(y))

    def describe(self) -> str:  # pragma: no cover - each model words its own log line
        raise NotImplementedError


def is_noise_model(obj: object) -> bool:
    """Whether ``obj`` is a noise model of this protocol (per-channel a and b, variance, describe)."""
    return isinstance(obj, PoissonGaussian) and len(tuple(obj.a)) == 3 and len(tuple(obj.b)) == 3
