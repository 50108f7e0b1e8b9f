"""Tone ``exposure`` (the default): the enhancement as a longer exposure.

A camera records light linearly and then encodes it with its tone curve (sRGB for JPEGs); a longer exposure
multiplies the recorded light by a gain k before that curve. So the enhancement undoes the curve, applies the gain
and re-encodes:
    S_enh = srgb(s(k · lin(R̂ ∘ L̂))),   L_enh = srgb(s(k · lin(L̂))),   k = lin(L_ref)^(−1/g),
s the highlight shoulder (:func:`~retinexgs.model.tones.curves.highlight_shoulder`; knee 1: the clip). g keeps its
role: at g = 1 the scene's full light L_ref maps to white (LR3M's L / max L, in linear light), a smaller g is a
longer exposure (log k = −log lin(L_ref) / g), so the EnhancementNet and ``--gamma`` work unchanged; ``--exposure X``
divides the light by X (k → k / X: 0.5 is one stop brighter) where the gamma tones scale g by X. A gamma curve on
sRGB values instead lifts the shadows more than the mid-tones (it flattens the image); a gain keeps the scene's
contrast as the longer exposure records it, up to the curve's clipping of highlights. One fused kernel (csrc:
``exposure_tone``) renders a frame.
"""
from __future__ import annotations

import weakref
from typing import Optional, Tuple

import torch
from torch import Tensor

from retinexgs.model.tones.base import Tone, _numbers, register
from retinexgs.model.tones.curves import srgb_to_linear
from retinexgs.model.tones.fused_curve import tone_curve

__all__ = ["ExposureTone", "log_lin_ref", "exposure_gain", "reference_gain", "exposure_linear"]


# Values derived from a reference tensor L_ref, by (id, name): (a weak reference to it, its version, dtype, device,
# the value). L_ref is a constant of the scene (a buffer set once from the 2D priors): log lin(L_ref) took ~12 scalar
# kernels at each of the 2–3 calls a training step, inside the loss graph (issue 65). An in-place change of the
# buffer bumps its version: computed anew. Keyed by identity: a tensor's == is elementwise (and a host sync).
_DERIVED: dict = {}
_RETIRED: list = []  # replaced values, kept alive: a CUDA graph captured before the change still reads their memory


def _derived(illum_ref: Tensor, name: str, like: Tensor, compute) -> Tensor:
    """``compute()`` once per (L_ref tensor, ``name``, version, ``like``'s dtype and device); a reference with a
    gradient is not cached."""
    if illum_ref.requires_grad:
        return compute()
    key = (illum_ref._version, like.dtype, like.device)
    hit = _DERIVED.get((id(illum_ref), name))
    if hit is None or hit[0]() is not illum_ref or hit[1] != key:
        for stale in [k for k, v in _DERIVED.items() if v[0]() is None]:  # references gone: their ids may recur
            _RETIRED.append(_DERIVED.pop(stale)[2])
        if hit is not None:
            _RETIRED.append(hit[2])
        hit = (weakref.ref(illum_ref), key, compute())
        _DERIVED[(id(illum_ref), name)] = hit
    return hit[2]


def log_lin_ref(illum_ref: Tensor, like: Tensor) -> Tensor:
    """log lin(L_ref), kept below 0 (L_ref < 1: a dark scene's light), in ``like``'s dtype and device; computed once
    per reference (and its version, dtype and device) where it has no gradient."""
    return _derived(illum_ref, "log_lin_ref", like,
                    lambda: torch.log(srgb_to_linear(illum_ref.to(like)).clamp_min(1e-6)).clamp_max(-1e-6))


def reference_gain(illum_ref: Tensor) -> Tensor:
    """The gain at g = 1, 1 / lin(L_ref) (:func:`exposure_gain`), in L_ref's dtype and device: the exposure that maps
    the scene's full light to white, a constant of the scene (computed once, as :func:`log_lin_ref`)."""
    return _derived(illum_ref, "reference_gain", illum_ref,
                    lambda: exposure_gain(illum_ref, illum_ref.new_ones(())))


def exposure_gain(illum_ref: Tensor, gamma: Tensor, log_ref: Optional[Tensor] = None) -> Tensor:
    """k = lin(L_ref)^(−1/g), the linear-light gain of tone ``exposure`` (``gamma`` of any shape). Capped at
    e^40 (everything but black is white long before): a tiny fixed ``--gamma`` would overflow k to inf, and
    inf · 0 on black pixels is NaN. ``log_ref``: log lin(L_ref) already computed (:func:`log_lin_ref`; the
    frame graph keeps it instead of a dozen scalar kernels per frame)."""
    log_ref = log_lin_ref(illum_ref, gamma) if log_ref is None else log_ref
    return torch.exp((-log_ref / gamma).clamp_max(40.0))


def exposure_linear(R: Tensor, L: Tensor, illum_ref: Tensor, gamma: Tensor, k: Optional[Tensor] = None) -> Tensor:
    """k · lin(R̂∘L̂): the linear light of tone ``exposure`` before the highlight shoulder and the sRGB
    curve (arguments as in :meth:`ExposureTone.map`; ``k``: the gain already computed). On this scale 1.0 is what the
    PNG shows as white when the shoulder is off (the clip); ``render --format exr`` writes it, and the white
    balance (:func:`~retinexgs.model.tones.curves.white_balance`) acts on it."""
    k = exposure_gain(illum_ref, gamma) if k is None else k
    return k * srgb_to_linear(R * L)


@register
class ExposureTone(Tone):
    """A gain in linear light set by g, the highlights rolled off by the shoulder (module docstring)."""

    name = "exposure"
    formula = "srgb(shoulder(k*lin(R*L))), k = lin(L_ref)^(-1/g)"
    fused_kernel = "exposure_tone"
    meter_applies = True
    needs_reference = True
    gain_curve = True  # map is tone_curve(R * L, exposure_gain(g), shoulder)

    def map(self, R: Tensor, L: Tensor, illum_ref: Tensor, gamma: Tensor, eps: float = 1e-3,
            shoulder: float = 1.0) -> Tuple[Tensor, Tensor]:
        k = exposure_gain(illum_ref, gamma)
        # srgb(s(k · lin(·))) as one kernel each way (fused_curve: in torch ~12 passes over the image each way)
        return tone_curve(R * L, k, shoulder), tone_curve(L, k, shoulder)

    def linear(self, R: Tensor, L: Tensor, illum_ref: Tensor, gamma: Tensor) -> Optional[Tensor]:
        return exposure_linear(R, L, illum_ref, gamma)

    def knee(self, shoulder: float) -> float:
        return shoulder

    def apply_exposure(self, gamma: Tensor, exposure, illum_ref: Tensor, log_ref: Optional[Tensor] = None) -> Tensor:
        """The gain divided by X, k' = k / X (X = 0.5: twice the light, one photographic stop), i.e. 1/g' = 1/g +
        log X / log lin(L_ref); a gain below 1 (darker than the capture) is not reached. Scaling g here would raise
        the gain to the power 1/X (X = 0.5 squares a gain of 30)."""
        if not torch.is_tensor(exposure) and float(exposure) == 1.0:
            return gamma  # exactly, as with no exposure given
        x = torch.as_tensor(exposure, dtype=gamma.dtype, device=gamma.device)
        log_ref = log_lin_ref(illum_ref, gamma) if log_ref is None else log_ref
        return 1.0 / (1.0 / gamma + torch.log(x) / log_ref).clamp_min(1e-3)

    def fused_gain(self, illum_ref: Tensor, gamma: Tensor, log_ref: Optional[Tensor] = None) -> Tensor:
        return exposure_gain(illum_ref, gamma, log_ref)

    def describe(self, gamma: Tensor, illum_ref: Tensor, shoulder: float, balanced: bool) -> str:
        k = exposure_gain(illum_ref.detach().double().cpu(), gamma)
        light = "W*k*lin(R*L)" if balanced else "k*lin(R*L)"
        curve = f"shoulder({light}, {shoulder:g})" if shoulder < 1.0 else light
        return (f"colour: enhanced as a longer exposure, srgb({curve}) with k = lin(L_ref)^(-1/g) = "
                f"({_numbers(k, '.4g')}), L_ref = {float(illum_ref):.4f}, g = ({_numbers(gamma, '.4f')})")
