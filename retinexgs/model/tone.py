"""The tone maths under its earlier module name: a re-export of :mod:`retinexgs.model.tones` (the tone objects and
their registry) and :mod:`retinexgs.model.tones.curves` (the shared light and noise maths), so that
``from retinexgs.model.tone import tone_map`` keeps working."""
from __future__ import annotations

from retinexgs.model.tones import TONES, Tone, apply_exposure, get_tone, register, tone_map
from retinexgs.model.tones.curves import (BLACK_TABLE_SIZE, Noise, black_table, box_mean, camera_mean,
                                          camera_mean_inverse, guided_filter, highlight_capped_mean,
                                          highlight_shoulder, linear_to_srgb, scene_linear, smooth_record,
                                          srgb_to_linear, white_balance)
from retinexgs.model.tones.exposure import exposure_gain, exposure_linear, log_lin_ref

__all__ = ["TONES", "Tone", "get_tone", "register", "srgb_to_linear", "linear_to_srgb", "highlight_shoulder",
           "camera_mean", "camera_mean_inverse", "black_table", "BLACK_TABLE_SIZE", "box_mean", "guided_filter",
           "smooth_record", "scene_linear", "highlight_capped_mean", "log_lin_ref", "exposure_gain", "apply_exposure",
           "exposure_linear", "white_balance", "tone_map", "Noise"]
