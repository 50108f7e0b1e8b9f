"""The light and noise maths the tones share (pure functions on tensors, with gradients): the highlight shoulder,
the camera's clipped-noise response and its black table, the edge-preserving filter of a render's residual noise,
the highlight-protecting meter and the white balance. The tones themselves live beside this module, one a module.

``shoulder`` a < 1 rolls the highlights off instead of clipping them, as a camera's tone curve does: linear light v
passes unchanged up to a and above it follows a + (1 − a)(1 − e^(−(v − a)/(1 − a))), which leaves a with slope 1 and
approaches white without reaching it (:func:`highlight_shoulder`). a = 1 is the clip. ``noise`` (a black table)
reads R̂ ∘ L̂ as the photos' average record rather than as light (:func:`scene_linear`); ``spread`` first takes the
render's own residual noise out of it with an edge-preserving filter (:func:`smooth_record`), since the table's
inverse doubles whatever error lies near black.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from torch import Tensor

from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear  # noqa: F401 (the tones' curves; re-exported)

__all__ = ["srgb_to_linear", "linear_to_srgb", "highlight_shoulder", "camera_mean", "camera_mean_inverse",
           "black_table", "BLACK_TABLE_SIZE", "box_mean", "guided_filter", "smooth_record", "scene_linear",
           "highlight_capped_mean", "white_balance", "Noise"]

# A :func:`black_table` [3, N] of a capture's Poisson–Gaussian noise (var = a·y + b per channel in linear light,
# :class:`retinexgs.train.noise.CaptureNoise`), as a tone's ``noise``; None: no correction.
Noise = Optional[Tensor]

# Gauss–Hermite rule (probabilists'): E[f(Z)] ≈ Σ w_i f(z_i) for Z ~ N(0, 1). Eight nodes put the clipped,
# sRGB-encoded mean within 0.001 of a Monte Carlo mean at every level of fountain-dark's sensor (1500 e⁻, 4 e⁻).
_GH_Z, _GH_W = np.polynomial.hermite_e.hermegauss(8)
_GH = tuple(zip(_GH_Z.tolist(), (_GH_W / _GH_W.sum()).tolist()))


def highlight_shoulder(v: Tensor, knee: float) -> Tensor:
    """Linear light v ≥ 0 with its highlights rolled off above ``knee`` (module docstring); knee ≥ 1: v as is
    (linear_to_srgb clips it). C¹ at the knee; the clamp inside the exponent keeps the branch that torch.where
    drops finite, so its gradient is never inf · 0."""
    if knee >= 1.0:
        return v
    span = 1.0 - knee
    rolled = knee + span * (1.0 - torch.exp(-(v - knee).clamp_min(0.0) / span))
    return torch.where(v > knee, rolled, v)


def camera_mean(x: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """What a camera records on average from sRGB-encoded light ``x``: E[srgb(max(0, lin(x) + n))], n ~ N(0,
    a·lin(x) + b) per channel (``a``, ``b`` broadcastable against ``x``: the capture's noise in linear light), by an
    8-node Gauss–Hermite rule.

    Why: a sensor's noise is clipped at black, so a dark photo's values average above the light that made them
    (about 0.4σ at black), and the sRGB curve's bend lowers the mid-tones' average a little. Equals ``x`` where
    the noise is 0 (to the encoding's precision)."""
    m = srgb_to_linear(x, clip=False)
    sigma = (a * m + b).clamp_min(1e-12).sqrt()
    out = None
    for z, w in _GH:
        term = w * linear_to_srgb(m + z * sigma, clip=False)
        out = term if out is None else out + term
    return out


def camera_mean_inverse(y: Tensor, a: Tensor, b: Tensor, iters: int = 40) -> Tensor:
    """The linear light μ ≥ 0 whose average record is ``y`` (sRGB, [0, 1]): camera_mean(srgb(μ)) = y, solved per
    value by bisection on srgb(μ) in [0, 1] (camera_mean rises with its argument); 0 where y lies below the record
    of black (a value darker than the noise's floor). No gradient: :func:`black_table` tabulates it."""
    with torch.no_grad():
        lo, hi = torch.zeros_like(y), torch.ones_like(y)
        for _ in range(iters):
            mid = 0.5 * (lo + hi)
            above = camera_mean(mid, a, b) > y
            hi = torch.where(above, mid, hi)
            lo = torch.where(above, lo, mid)
        return srgb_to_linear(0.5 * (lo + hi))


BLACK_TABLE_SIZE = 4096


def black_table(a=None, b=None, size: int = BLACK_TABLE_SIZE) -> Tensor:
    """[3, size] float32: per channel, the linear light whose average record is each of ``size`` sRGB values evenly
    spaced over [0, 1], under the noise var = a·y + b (``a``, ``b``: three numbers each). Without noise, lin(y)
    itself: the identity of :func:`scene_linear`. Built in float64 on the CPU, once per scene."""
    y = torch.linspace(0.0, 1.0, size, dtype=torch.float64).expand(3, size)
    if a is None or b is None:
        return srgb_to_linear(y).float()
    a_ = torch.as_tensor(a, dtype=torch.float64).reshape(3, 1)
    b_ = torch.as_tensor(b, dtype=torch.float64).reshape(3, 1)
    return camera_mean_inverse(y.contiguous(), a_, b_).float()


def box_mean(x: Tensor, radius: int) -> Tensor:
    """The mean of [B,C,H,W] ``x`` over (2r+1)² windows, the border reflected (H, W > ``radius``)."""
    r = int(radius)
    return torch.nn.functional.avg_pool2d(torch.nn.functional.pad(x, (r, r, r, r), mode="reflect"), 2 * r + 1, 1)


def guided_filter(p: Tensor, radius: int, eps: Tensor) -> Tensor:
    """He, Sun & Tang's guided filter (ECCV 2010, Eq. 1-8) with each channel its own guide: in each window, ``p`` ≈
    a·p + b by least squares with a ridge ε on a, so a = var / (var + ε) (the local Wiener filter); the output
    averages the windows' fits. Where the window varies much more than ε (an edge) the output follows it, where it
    varies less (flat, noisy) it is the window's mean; exactly the identity at ε = 0.

    Args:
        p: [B,C,H,W] the image to filter.
        radius: the window's half size r, in pixels (H, W > r).
        eps: ε ≥ 0, broadcastable against ``p`` (e.g. a per-pixel noise variance [B,C,H,W]).
    """
    m_p = box_mean(p, radius)
    var = (box_mean(p * p, radius) - m_p * m_p).clamp_min(0.0)  # float rounding can take it below 0
    a = var / (var + eps).clamp_min(1e-20)
    b = m_p - a * m_p
    return box_mean(a, radius) * p + box_mean(b, radius)


def smooth_record(RL: Tensor, spread: Tensor, radius: int) -> Tensor:
    """R̂∘L̂ [H,W,3] (sRGB) with the render's residual noise taken out: a :func:`guided_filter` in linear light, ε per
    pixel the window's mean of ``spread`` [2,3]'s a·x + b per channel (the capture's
    noise variance at the training images' scale divided by the number of training views: the render averages the
    views, so that is its residual noise where every view sees the point, the least it has). The identity where
    ``spread`` is 0 (a clean capture), where the image is smaller than the window or where ``radius`` is 0."""
    if radius <= 0 or RL.dim() != 3 or min(RL.shape[0], RL.shape[1]) <= radius:
        return RL
    x = srgb_to_linear(RL).permute(2, 0, 1).unsqueeze(0)
    spread = spread.to(x)
    eps = box_mean(spread[0].reshape(1, 3, 1, 1) * x + spread[1].reshape(1, 3, 1, 1), radius)
    y = guided_filter(x, radius, eps)
    return linear_to_srgb(y[0].permute(1, 2, 0))


def scene_linear(RL: Tensor, table: Noise = None) -> Tensor:
    """The linear light of R̂∘L̂ [..., 3] that the enhancement exposes: lin(R̂∘L̂), or through a :func:`black_table`
    [3, N] the light whose average record R̂∘L̂ is: the render matches the photos' mean, which clipped sensor noise
    lifts above black (``model.enhancement.debias_black``). Linear interpolation in the table: a few elementwise
    kernels and gathers, differentiable in R̂∘L̂, no host sync."""
    if table is None:
        return srgb_to_linear(RL)
    table = table.to(RL)
    n = table.shape[-1]
    pos = RL.clamp(0.0, 1.0) * (n - 1)
    i0 = pos.detach().floor().clamp(0, n - 2)
    t = pos - i0
    i0 = i0.long()
    flat = RL.shape[:-1].numel()
    rows = i0.reshape(flat, 3).t()  # [3, P]
    lo, hi = table.gather(1, rows), table.gather(1, rows + 1)
    lo, hi = lo.t().reshape(RL.shape), hi.t().reshape(RL.shape)
    return lo + (hi - lo) * t


def highlight_capped_mean(RL: Tensor, target: float, share: float, shoulder: float = 1.0,
                          noise: Noise = None) -> Tensor:
    """The exposure meter's target for one image [..., 3] of R̂∘L̂ under tone ``exposure``: ``target`` (the mean an
    averaging meter asks for), lowered to the mean of the exposure that takes exactly ``share`` of the pixels past
    white (their brightest channel's linear light at 1 before the ``shoulder``) where that exposure is shorter.
    A camera's highlight-protecting meter: expose for the average unless more than ``share`` of the frame would
    blow out. The scale of R̂∘L̂ drops out (the exposure is found from its own quantile), so the result depends only
    on the image's light distribution. ``noise``: the light as :func:`scene_linear` reads it. A 0-d tensor, no
    gradient; a sort (no host sync: graph-capturable)."""
    with torch.no_grad():
        lin = scene_linear(RL.detach().float(), noise)
        peak = lin.amax(-1).flatten()
        rank = min(peak.numel() - 1, max(0, int(round((1.0 - share) * (peak.numel() - 1)))))
        white = torch.sort(peak).values[rank].clamp_min(1e-8)
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
