"""The sRGB transfer curve (IEC 61966-2-1), one definition for numpy arrays and torch tensors alike: the sensor
model and the camera-raw preview use it on arrays, the tone map and the losses on tensors (with gradients)."""
from __future__ import annotations

from typing import TypeVar

import numpy as np
import torch

Image = TypeVar("Image", np.ndarray, torch.Tensor)

# The curve's breakpoints: sRGB 0.04045 is linear 0.04045 / 12.92 = 0.0031308.
_S_KNEE, _L_KNEE, _SLOPE, _A, _A1, _GAMMA = 0.04045, 0.0031308, 12.92, 0.055, 1.055, 2.4


def _limit(x: Image, clip: bool) -> Image:
    if isinstance(x, torch.Tensor):
        return x.clamp(0.0, 1.0) if clip else x.clamp_min(0.0)
    return np.clip(x, 0.0, 1.0) if clip else np.maximum(x, 0.0)


def _where(cond, a: Image, b: Image) -> Image:
    return torch.where(cond, a, b) if isinstance(a, torch.Tensor) else np.where(cond, a, b)


def _floor(x: Image, v: float) -> Image:
    return x.clamp_min(v) if isinstance(x, torch.Tensor) else np.maximum(x, v)


def srgb_to_linear(x: Image, clip: bool = True) -> Image:
    """sRGB values in [0, 1] -> linear light. ``clip=False``: values above 1 follow the same curve (negatives are
    still clamped). The floor inside the power keeps the branch that ``where`` drops finite, so a gradient through
    it is never inf · 0."""
    x = _limit(x, clip)
    return _where(x <= _S_KNEE, x / _SLOPE, ((_floor(x, _S_KNEE) + _A) / _A1) ** _GAMMA)


def linear_to_srgb(x: Image, clip: bool = True) -> Image:
    """Linear light -> sRGB, clipped to [0, 1] first (what a camera does to light past white). ``clip=False``:
    light past white keeps rising along the curve (a loss that must keep a gradient there)."""
    x = _limit(x, clip)
    return _where(x <= _L_KNEE, _SLOPE * x, _A1 * _floor(x, _L_KNEE) ** (1.0 / _GAMMA) - _A)


def linear_to_srgb_extended(x: Image) -> Image:
    """Linear light -> sRGB without any clip, for values a raw file holds beyond [0, 1]: below 0 (noise around
    black, kept zero-mean) along the curve's linear segment (12.92·x), above 1 along its power segment. Monotone
    and exactly inverted by :func:`srgb_to_linear_extended`; equal to :func:`linear_to_srgb` on [0, 1]."""
    return _where(x <= _L_KNEE, _SLOPE * x, _A1 * _floor(x, _L_KNEE) ** (1.0 / _GAMMA) - _A)


def srgb_to_linear_extended(x: Image) -> Image:
    """The inverse of :func:`linear_to_srgb_extended` (no clip: negative values map to negative light)."""
    return _where(x <= _S_KNEE, x / _SLOPE, ((_floor(x, _S_KNEE) + _A) / _A1) ** _GAMMA)
