"""The capture's sensor noise, measured from its own training photos at set-up, and the two things training
does with it (issue 32; each a config switch with its reason in configs/default.yaml):

- ``loss.rec_noise_floor``: the reconstruction term's SSIM compares the render with the photo at an exposure
  (:func:`retinexgs.train.losses.exposed`, gain 1 / lin(L_ref)). That gain is capped where the exposed photos'
  noise reaches SSIM's own stabilising constant, σ = K2 = 0.03 on a [0, 1] range: above the cap the SSIM would
  ask the render to copy each view's noise, which a 3D model can only do by growing Gaussians for it (speckle in
  every novel view). On a clean capture (LOM: σ < 0.01 at the full gain) nothing changes.
- ``loss.rec_camera_noise``: the render is compared with the photo through the camera's average response to it
  (:func:`retinexgs.train.losses.camera_expectation`) under the Poisson–Gaussian noise measured here, so the
  blacks of the output are not lifted by the positive mean of clipped noise.

Measured on the first :data:`MEASURED_VIEWS` training views (as they are read, one at a time): per view,
:func:`retinexgs.data.sensor.estimate_noise` (``var = a·y + b`` per channel in linear light) and the exposed
noise σ (Immerkær, the largest channel) at each gain of :data:`GAINS`; the capture's figures are the medians over
those views. Through 8-bit JPEG both see about 0.4–0.9 of the true σ (docs/experiments/2026-11-26-noise-estimate.md):
the cap errs towards the exposed SSIM, the black level towards too little correction.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
from torch import Tensor

from retinexgs.data.sensor import estimate_noise
from retinexgs.train.losses import exposed, noise_variance

MEASURED_VIEWS = 8
# Exposure gains at which the exposed noise is measured: 1 to 256 in half stops (a scene's gain 1 / lin(L_ref) is
# 2–60 on the dev scenes); the cap is interpolated between them, log-linearly.
GAINS: Tuple[float, ...] = tuple(2.0 ** (k / 2.0) for k in range(17))
SSIM_K2 = 0.03  # SSIM's C2 = (K2 · range)², range 1: the noise σ at which the noise variance equals C2


@dataclass(frozen=True)
class CaptureNoise:
    """A capture's noise: per channel ``var = a·y + b`` in linear light, and the exposed photos' noise σ at
    each of ``gains``."""

    a: Tuple[float, float, float]
    b: Tuple[float, float, float]
    gains: Tuple[float, ...]
    sigma: Tuple[float, ...]
    views: int

    def gain_cap(self, limit: float = SSIM_K2) -> float:
        """The largest exposure gain at which the exposed photos' noise σ is at most ``limit`` (log-linear
        between the measured gains); inf when even the largest measured gain stays below it."""
        if self.sigma[0] > limit:
            return self.gains[0]
        for k in range(1, len(self.gains)):
            if self.sigma[k] > limit:
                s0, s1 = math.log(self.sigma[k - 1]), math.log(self.sigma[k])
                t = (math.log(limit) - s0) / (s1 - s0) if s1 > s0 else 0.0
                return math.exp(math.log(self.gains[k - 1]) + t * (math.log(self.gains[k]) - math.log(self.gains[k - 1])))
        return math.inf

    def camera(self, device: torch.device) -> Tuple[Tensor, Tensor]:
        """(a, b) as [1,3,1,1] float32 tensors on ``device`` (:func:`retinexgs.train.losses.camera_expectation`)."""
        return (torch.tensor(self.a, dtype=torch.float32, device=device).reshape(1, 3, 1, 1),
                torch.tensor(self.b, dtype=torch.float32, device=device).reshape(1, 3, 1, 1))

    def state_dict(self) -> Dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_state(cls, state: Dict) -> "CaptureNoise":
        return cls(tuple(state["a"]), tuple(state["b"]), tuple(state["gains"]), tuple(state["sigma"]),
                   int(state["views"]))  # type: ignore[arg-type]

    def describe(self) -> str:
        """One line for the training log."""
        sig = ", ".join(f"{math.sqrt(max(a * 0.01 + b, 0.0)):.4f}" for a, b in zip(self.a, self.b))
        cap = self.gain_cap()
        return (f"capture noise (median of {self.views} views): σ at linear 0.01 = {sig} (R, G, B); exposed SSIM "
                f"gain capped at {'none' if math.isinf(cap) else f'{cap:.2f}'} (noise σ ≤ {SSIM_K2})")


def exposed_noise_sigma(S: Tensor, gains: Tuple[float, ...] = GAINS) -> List[float]:
    """The noise σ of one photo ``S`` [H,W,3] (sRGB, [0,1]) exposed by each gain (the largest channel's)."""
    x = S.detach().float().permute(2, 0, 1).unsqueeze(0)
    out = []
    for g in gains:
        var = noise_variance(exposed(x, x.new_tensor(g)))
        out.append(float(var.amax().sqrt()))
    return out


class NoiseMeter:
    """Gathers :class:`CaptureNoise` from the first ``views`` photos that pass through :meth:`add`."""

    def __init__(self, views: int = MEASURED_VIEWS) -> None:
        self.max_views = views
        self._a: List[Tuple[float, ...]] = []
        self._b: List[Tuple[float, ...]] = []
        self._sigma: List[List[float]] = []

    def add(self, S: Tensor) -> None:
        if len(self._sigma) >= self.max_views or S.shape[0] < 8 or S.shape[1] < 8:
            return
        est = estimate_noise(S.detach().float().cpu().numpy())
        self._a.append(est.a)
        self._b.append(est.b)
        self._sigma.append(exposed_noise_sigma(S))

    def result(self) -> Optional[CaptureNoise]:
        """The medians over the measured views; None when no view was measured."""
        if not self._sigma:
            return None
        a = tuple(float(v) for v in np.median(np.array(self._a), axis=0))
        b = tuple(float(v) for v in np.median(np.array(self._b), axis=0))
        sigma = tuple(float(v) for v in np.median(np.array(self._sigma), axis=0))
        return CaptureNoise(a, b, GAINS, sigma, len(self._sigma))  # type: ignore[arg-type]


__all__ = ["CaptureNoise", "NoiseMeter", "exposed_noise_sigma", "GAINS", "SSIM_K2", "MEASURED_VIEWS"]
