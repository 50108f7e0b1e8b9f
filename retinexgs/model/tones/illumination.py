"""Tone ``illumination`` (the paper, ``--config paper``): a gamma on the normalised light,
L_enh = ℓ^g, S_enh = clip(R̂ ∘ L_enh, 0, 1), ℓ = clip(L̂ / L_ref, 0, 1) floored at ``eps`` (so the power's gradient
stays finite at 0)."""
from __future__ import annotations

from typing import Tuple

from torch import Tensor

from retinexgs.model.tones.base import Tone, register

__all__ = ["IlluminationTone"]


@register
class IlluminationTone(Tone):
    """The paper's R̂ ∘ (L̂ / L_ref)^g (module docstring); :class:`~retinexgs.model.tones.signal.SignalTone` puts
    the gamma on R̂ too."""

    name = "illumination"
    formula = "R*clip(L/L_ref,0,1)^g"

    def reflectance(self, R: Tensor, gamma: Tensor, eps: float) -> Tensor:
        """What multiplies the enhanced light: R̂ itself here."""
        return R

    def map(self, R: Tensor, L: Tensor, illum_ref: Tensor, gamma: Tensor, eps: float = 1e-3,
            shoulder: float = 1.0) -> Tuple[Tensor, Tensor]:
        light = (L / illum_ref.to(L)).clamp(0.0, 1.0).clamp_min(eps) ** gamma
        return (self.reflectance(R, gamma, eps) * light).clamp(0.0, 1.0), light
