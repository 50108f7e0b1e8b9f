"""The light maths the tones share (pure functions on tensors, with gradients): the highlight shoulder and the white
balance (the highlight-protecting meter: :mod:`.meter`). The tones themselves live beside this module, one a module.

``shoulder`` a < 1 rolls the highlights off instead of clipping them, as a camera's tone curve does: linear light v
passes unchanged up to a and above it follows a + (1 − a)(1 − e^(−(v − a)/(1 − a))), which leaves a with slope 1 and
approaches white without reaching it (:func:`highlight_shoulder`). a = 1 is the clip.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear  # noqa: F401 (the tones' curves; re-exported)

__all__ = ["srgb_to_linear", "linear_to_srgb", "highlight_shoulder", "white_balance"]


def highlight_shoulder(v: Tensor, knee: float) -> Tensor:
    """Linear light v ≥ 0 with its highlights rolled off above ``knee`` (module docstring); knee ≥ 1: v as is
    (linear_to_srgb clips it). C¹ at the knee; the clamp inside the exponent keeps the branch that torch.where
    drops finite, so its gradient is never inf · 0."""
    if knee >= 1.0:
        return v
    span = 1.0 - knee
    rolled = knee + span * (1.0 - torch.exp(-(v - knee).clamp_min(0.0) / span))
    return torch.where(v > knee, rolled, v)


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
