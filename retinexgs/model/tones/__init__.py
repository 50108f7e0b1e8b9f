"""The enhancement's tones (``model.enhancement.tone``): how g turns the rendered R̂, L̂ into the enhanced image.

One :class:`Tone` object a tone holds everything the package asks of it: its map (light -> display, with the
enhanced light L_enh), its linear form (``render --format exr``, the white balance), its exposure rule
(``--exposure``), its highlight knee, the fused kernel that renders a frame of it, the formula text for the PLY
comment and logs, and whether the highlight meter applies to it. Training, ``render``/``eval``/the viewer (through
the fused frame renderer), the export bake and the 2D proxy all call the same object, so they cannot drift apart.

Built in, with ℓ = clip(L̂ / L_ref, 0, 1) (L_ref: the scene's full light, a constant of the scene):
- ``illumination`` (the paper):  S_enh = clip(R̂ ∘ ℓ^g)                       (:mod:`.illumination`)
- ``signal``:                    S_enh = clip(R̂^g ∘ ℓ^g)                     (:mod:`.signal`)
- ``exposure`` (the default):    S_enh = srgb(s(k · lin(R̂ ∘ L̂))), k = lin(L_ref)^(−1/g)   (:mod:`.exposure`)

A new tone is one module: subclass :class:`Tone`, set ``name`` and ``formula`` (and the attributes that differ
from the defaults), implement ``map``, decorate with :func:`register`, and import the module here (or, for a
tone outside the package, anywhere before the config is loaded): the config loader accepts its name from
:data:`TONES`. The shared light maths is in :mod:`.curves`.
"""
from __future__ import annotations

from typing import Optional, Tuple, Union

from torch import Tensor

from retinexgs.model.tones.base import TONES, Tone, config_problem, get_tone, register
# The built-in tones register on import, in this order (the order error messages list them in).
from retinexgs.model.tones.illumination import IlluminationTone
from retinexgs.model.tones.signal import SignalTone
from retinexgs.model.tones.exposure import ExposureTone  # noqa: I001 (registration order)

__all__ = ["Tone", "TONES", "register", "get_tone", "config_problem", "tone_map", "apply_exposure",
           "IlluminationTone", "SignalTone", "ExposureTone"]


def tone_map(R: Tensor, L: Tensor, illum_ref: Tensor, gamma: Tensor, tone: Union[str, Tone], eps: float = 1e-3,
             shoulder: float = 1.0) -> Tuple[Tensor, Tensor]:
    """(S_enh, L_enh) of the tone ``tone`` (a name or a :class:`Tone`): :meth:`Tone.map`. ValueError for a name
    that is not registered."""
    return get_tone(tone).map(R, L, illum_ref, gamma, eps, shoulder)


def apply_exposure(gamma: Tensor, exposure, illum_ref: Tensor, tone: Union[str, Tone],
                   log_ref: Optional[Tensor] = None) -> Tensor:
    """g after the user's exposure factor X > 0 (``--exposure``, the viewer's slider; < 1 brighter, > 1 darker)
    under the tone ``tone`` (a name or a :class:`Tone`): :meth:`Tone.apply_exposure`. ``exposure`` may be a float
    or a tensor (the frame graph keeps it on the device); ``log_ref``: log lin(L_ref) already computed."""
    return get_tone(tone).apply_exposure(gamma, exposure, illum_ref, log_ref)
