"""Tone ``signal``: the gamma on the whole signal, L_enh = ℓ^g, S_enh = clip(R̂^g ∘ L_enh, 0, 1) (R̂ floored at
``eps`` before the power), ℓ as in :mod:`~retinexgs.model.tones.illumination`."""
from __future__ import annotations

from torch import Tensor

from retinexgs.model.tones.base import register
from retinexgs.model.tones.illumination import IlluminationTone

__all__ = ["SignalTone"]


@register
class SignalTone(IlluminationTone):
    """(R̂ ∘ ℓ)^g, clipped (module docstring)."""

    name = "signal"
    formula = "R^g*clip(L/L_ref,0,1)^g"

    def reflectance(self, R: Tensor, gamma: Tensor, eps: float) -> Tensor:
        return R.clamp_min(eps) ** gamma
