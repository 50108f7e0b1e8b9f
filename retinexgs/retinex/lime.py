"""LIME baseline (Guo, Li, Ling, "LIME: Low-Light Image Enhancement via Illumination Map Estimation",
IEEE TIP 2017): a fast decomposer without denoising.

L̂ = max over RGB (LIME eq. 2), refined by the same structure-aware SPD solve as LR3M (LIME eq. 8/9,
weights of strategy III), floored, optionally raised to a gamma; R = S / L clipped to [0,1] (LIME eq. 1).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import torch

from retinexgs.retinex.base import Decomposer
from retinexgs.retinex.illumination import max_rgb, percentile_scale, refine_illumination


@dataclass(frozen=True)
class LIMEParams:
    """LIME parameters (α = 0.15, ε = 1e-3 and Gaussian σ = 2 as in the LIME paper)."""

    alpha: float = 0.15       # smoothness weight (β of the shared solver)
    eps: float = 1e-3         # ε in a_d = α/(|∇L̂|+ε), on the normalised L̂
    weight_sigma: float = 2.0  # Gaussian σ (px) on ∇L̂ before the weights
    gamma: float = 1.0        # L ← L^γ before dividing (LIME uses 0.8 for display; 1 keeps R∘L = S)
    l_floor: float = 0.02     # L >= l_floor × 99th percentile of L (avoids dividing by ~0)
    cg_tol: float = 1e-4
    cg_max_iter: int = 300


class LIME(Decomposer):
    """Max-RGB illumination + structure-aware refinement; R = S / L."""

    name = "lime"
    Params = LIMEParams

    def _decompose_batch(self, s: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        p: LIMEParams = self.params
        l = refine_illumination(max_rgb(s), p.alpha, p.eps, p.weight_sigma, p.cg_tol, p.cg_max_iter)
        q = percentile_scale(l)
        l = torch.maximum(l, p.l_floor * q)
        if p.gamma != 1.0:
            # Apply the gamma on the normalised map so the result does not depend on exposure.
            l = (l / q) ** p.gamma * q
        return (s / l).clamp(0.0, 1.0), l


def lime_decompose(image: torch.Tensor, params: Optional[LIMEParams] = None, **overrides) -> Tuple[torch.Tensor, torch.Tensor]:
    """Functional shortcut: ``LIME(params, **overrides).decompose(image)``."""
    return LIME(params, **overrides).decompose(image)
