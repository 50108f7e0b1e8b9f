"""The light maths the tones share (pure functions on tensors, with gradients): the highlight shoulder, the
highlight-protecting meter and the white balance. The tones themselves live beside this module, one a module.

``shoulder`` a < 1 rolls the highlights off instead of clipping them, as a camera's tone curve does: linear light v
passes unchanged up to a and above it follows a + (1 − a)(1 − e^(−(v − a)/(1 − a))), which leaves a with slope 1 and
approaches white without reaching it (:func:`highlight_shoulder`). a = 1 is the clip.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear  # noqa: F401 (the tones' curves; re-exported)

__all__ = ["srgb_to_linear", "linear_to_srgb", "highlight_shoulder", "highlight_capped_mean", "white_balance"]


def highlight_shoulder(v: Tensor, knee: float) -> Tensor:
    """Linear light v ≥ 0 with its highlights rolled off above ``knee`` (module docstring); knee ≥ 1: v as is
    (linear_to_srgb clips it). C¹ at the knee; the clamp inside the exponent keeps the branch that torch.where
    drops finite, so its gradient is never inf · 0."""
    if knee >= 1.0:
        return v
    span = 1.0 - knee
    rolled = knee + span * (1.0 - torch.exp(-(v - knee).clamp_min(0.0) / span))
    return torch.where(v > knee, rolled, v)


def highlight_capped_mean(RL: Tensor, target: float, share: float, shoulder: float = 1.0) -> Tensor:
    """The exposure meter's target for one image [..., 3] of R̂∘L̂ under tone ``exposure``: ``target`` (the mean an
    averaging meter asks for), lowered to the mean of the exposure that takes exactly ``share`` of the pixels past
    white (their brightest channel's linear light at 1 before the ``shoulder``) where that exposure is shorter.
    A camera's highlight-protecting meter: expose for the average unless more than ``share`` of the frame would
    blow out. The scale of R̂∘L̂ drops out (the exposure is found from its own quantile), so the result depends only
    on the image's light distribution. A 0-d tensor, no gradient; a sort (no host sync: graph-capturable)."""
    # The curves as one kernel each (fused_curve, which imports this module: hence here); on the CPU its twin gives
    # lin bit for bit and the division below keeps CPU training as it was. On the GPU the meter's ~20 torch passes
    # over the image were ~15 % of a step's traffic (issue 65).
    from retinexgs.model.tones import fused_curve

    with torch.no_grad():
        RL = RL.detach().float()
        lin = fused_curve.to_linear(RL, "clip")
        peak = lin.amax(-1).flatten()
        rank = min(peak.numel() - 1, max(0, int(round((1.0 - share) * (peak.numel() - 1)))))
        white = torch.sort(peak).values[rank].clamp_min(1e-8)
        if fused_curve.runs_fused(RL):
            capped = fused_curve.tone_curve(RL, white.reciprocal(), shoulder, "clip", "clip").mean()
        else:
            capped = linear_to_srgb(highlight_shoulder(lin / white, shoulder)).mean()
        return capped.clamp(max=float(target))


def white_balance(light: Tensor, balance: Optional[Tensor]) -> Tensor:
    """Linear light [..., 3] (Rec.709 primaries) under a white-balance edit: ``balance`` is per-channel gains [3]
    or a 3×3 matrix acting on the RGB column (a temperature's chromatic adaptation); both leave a neutral's green
    unchanged (:mod:`retinexgs.model.white_balance`). None, gains exactly (1, 1, 1) or exactly the identity:
    ``light`` itself, the same tensor (as trained, bit for bit)."""
    if balance is None:
        return light
    balance = torch.as_tensor(balance).to(light)
    if balance.dim() == 1:
        return light if bool((balance == 1.0).all()) else light * balance
    if torch.equal(balance, torch.eye(3, dtype=balance.dtype, device=balance.device)):
        return light
    return light @ balance.t()
