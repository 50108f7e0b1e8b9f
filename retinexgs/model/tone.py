"""The tone maths under its earlier module name: a re-export of :mod:`retinexgs.model.tones` (the tone objects and
their registry), :mod:`retinexgs.model.tones.curves` (the shared light maths) and the exposure meter, so that
``from retinexgs.model.tone import tone_map`` keeps working."""
from __future__ import annotations

from retinexgs.model.tones import TONES, Tone, apply_exposure, get_tone, register, tone_map
from retinexgs.model.tones.curves import highlight_shoulder, linear_to_srgb, srgb_to_linear, white_balance
from retinexgs.model.tones.exposure import exposure_gain, exposure_linear, log_lin_ref
from retinexgs.model.tones.meter import highlight_capped_mean

__all__ = ["TONES", "Tone", "get_tone", "register", "srgb_to_linear", "linear_to_srgb", "highlight_shoulder",
           "highlight_capped_mean", "log_lin_ref", "exposure_gain", "apply_exposure",
           "exposure_linear", "white_balance", "tone_map"]
