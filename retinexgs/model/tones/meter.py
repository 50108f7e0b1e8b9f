"""The exposure meter of tone ``exposure``: the target mean L_exp meters towards, capped so that highlights do not
blow out (:func:`highlight_capped_mean`). Its own module: it uses both the shared curves (:mod:`.curves`) and their
fused kernel (:mod:`.fused_curve`, which imports :mod:`.curves`)."""
from __future__ import annotations

import torch
from torch import Tensor

from retinexgs.kth_value import kth_smallest
from retinexgs.model.tones import fused_curve
from retinexgs.model.tones.curves import highlight_shoulder, linear_to_srgb

__all__ = ["highlight_capped_mean"]


def highlight_capped_mean(RL: Tensor, target: float, share: float, shoulder: float = 1.0) -> Tensor:
    """The exposure meter's target for one image [..., 3] of R̂∘L̂ under tone ``exposure``: ``target`` (the mean an
    averaging meter asks for), lowered to the mean of the exposure that takes exactly ``share`` of the pixels past
    white (their brightest channel's linear light at 1 before the ``shoulder``) where that exposure is shorter.
    A camera's highlight-protecting meter: expose for the average unless more than ``share`` of the frame would
    blow out. The scale of R̂∘L̂ drops out (the exposure is found from its own quantile), so the result depends only
    on the image's light distribution. A 0-d tensor, no gradient; a selection (no host sync: graph-capturable)."""
    # The curves as one kernel each where tone_curve runs its kernel (the GPU: the meter's ~20 torch passes over the
    # image were ~15 % of a step's traffic, issue 65); on the CPU its twin gives lin bit for bit and the division
    # below keeps CPU training as it was.
    with torch.no_grad():
        RL = RL.detach().float()
        lin = fused_curve.to_linear(RL, "clip")
        peak = lin.amax(-1).flatten()
        rank = min(peak.numel() - 1, max(0, int(round((1.0 - share) * (peak.numel() - 1)))))
        # the (rank+1)-th smallest: a selection, not a sort of the whole image (torch's kthvalue took 76 ms of a
        # 12 MP step on the GPU: retinexgs/kth_value.py)
        white = kth_smallest(peak, rank + 1).clamp_min(1e-8)
        if fused_curve.runs_fused(RL):
            capped = fused_curve.tone_curve(RL, white.reciprocal(), shoulder, "clip", "clip").mean()
        else:
            capped = linear_to_srgb(highlight_shoulder(lin / white, shoulder)).mean()
        return capped.clamp(max=float(target))
