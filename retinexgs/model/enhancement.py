"""EnhancementNet: content-adaptive gamma for the rendered illumination map (paper Sec. II.D, Fig. 3).

A small CNN looks at the rendered illumination map L̂ and predicts one gamma per image and per channel;
in the paper the enhanced illumination is L_enh = L̂^g and the output image S_enh = R̂ ∘ L_enh (the default
tone instead sets a linear-light gain from g: :mod:`retinexgs.model.tone`). It is trained only by the
unsupervised losses of Eq. 7 (see :func:`retinexgs.train.losses.enhancement_loss`).

Layout: ``L`` is [B,3,H,W] (or [B,1,H,W]) float in [0, 1]; gamma is [B,C,1,1] and broadcasts against L.
Use ``x.permute(2, 0, 1)[None]`` to turn a rendered [H,W,3] map into [1,3,H,W].

Gamma range: g = g_min + (g_max − g_min)·sigmoid(z), [0.1, 1.0] for the gamma tones (the default config's
exposure tone uses [0.25, 2.0]). With L̂ ∈ (0, 1), g < 1 lifts dark illumination and g = 1 leaves it
unchanged; the net never darkens (g ≤ 1) and 0.1 bounds the lift (0.02^0.1 ≈ 0.68). The last layer starts at
zero weights with its bias set so that the initial gamma is ``init_gamma`` (default 0.4) for every input.

Features: the network sees L̂ and its normalised logarithm log(L̂)/log(1/eps_in) — because
L̂^g = exp(g·log L̂), the gamma that reaches a target exposure depends on log L̂, and the log channel
gives the dark range (L̂ ~ 0.02–0.3) usable contrast. The fixed input transform adds no parameters.
The input is first area-downsampled so that its longer side is at most ``max_side`` (default 128),
then three stride-2 3×3 convolutions (widths 16, 32, 32) and a global average pool feed a linear layer
that outputs C gamma logits: cost is independent of the rendered resolution.
"""
from __future__ import annotations

import math
from typing import List, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["EnhancementNet", "area_pool"]


def area_pool(x: torch.Tensor, size: Tuple[int, int]) -> torch.Tensor:
    """``F.adaptive_avg_pool2d(x, size)`` for ``x`` [B,C,H,W]; where ``size`` divides H and W the same windows' means
    as one reduction over a view (the adaptive kernel took 31 µs of a 3 ms fox-dark step on the render's
    channels-last [1,3,360,640], experiments/notes/2026-11-30-fused-enhance.md)."""
    (h, w), (oh, ow) = x.shape[-2:], size
    if h % oh or w % ow:
        return F.adaptive_avg_pool2d(x, size)
    return x.unflatten(-1, (ow, w // ow)).unflatten(-3, (oh, h // oh)).mean(dim=(-3, -1))


class EnhancementNet(nn.Module):
    """Predict a per-image, per-channel gamma from an illumination map; see the module docstring.

    Args:
        channels: channels of L̂ (3 for RGB illumination, 1 for grey).
        widths: conv widths of the three stride-2 stages.
        gamma_range: (g_min, g_max), 0 < g_min < g_max.
        init_gamma: initial gamma for any input, strictly inside gamma_range.
        max_side: the input is area-downsampled to at most this many pixels on its longer side.
        eps: floor under L̂ before the gamma tones' power (:func:`retinexgs.model.tone.tone_map`: keeps its
            gradient finite at 0).
        eps_in: floor for the log feature.
        per_view: True (the paper): g is predicted from each view's L̂. False: one g for the whole scene, a
            learned constant (the output layer's bias; the convolutions are unused), so every view, novel ones
            included, gets the same exposure.
    """

    def __init__(self, channels: int = 3, widths: Tuple[int, int, int] = (16, 32, 32),
                 gamma_range: Tuple[float, float] = (0.1, 1.0), init_gamma: float = 0.4,
                 max_side: int = 128, eps: float = 1e-3, eps_in: float = 1e-3, per_view: bool = True) -> None:
        super().__init__()
        g_min, g_max = float(gamma_range[0]), float(gamma_range[1])
        if not 0.0 < g_min < g_max:
            raise ValueError("gamma_range must satisfy 0 < g_min < g_max")
        if not g_min < init_gamma < g_max:
            raise ValueError("init_gamma must lie strictly inside gamma_range")
        self.channels, self.g_min, self.g_max = int(channels), g_min, g_max
        self.max_side, self.eps, self.eps_in = int(max_side), float(eps), float(eps_in)
        self.per_view = bool(per_view)
        c1, c2, c3 = widths
        self.features = nn.Sequential(
            nn.Conv2d(2 * self.channels, c1, 3, stride=2, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(c1, c2, 3, stride=2, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(c2, c3, 3, stride=2, padding=1), nn.ReLU(inplace=True),
            nn.AdaptiveAvgPool2d(1))
        self.out = nn.Linear(c3, self.channels)
        t = (init_gamma - g_min) / (g_max - g_min)
        nn.init.zeros_(self.out.weight)  # gradients still reach it (features are non-zero)
        nn.init.constant_(self.out.bias, math.log(t / (1.0 - t)))

    def used_parameters(self) -> List[nn.Parameter]:
        """The parameters the output depends on: all of them, or only the output bias with ``per_view`` off
        (what a captured training step may differentiate: each must get a gradient)."""
        return list(self.parameters()) if self.per_view else [self.out.bias]

    def _check(self, L: torch.Tensor) -> None:
        if L.dim() != 4 or L.shape[1] != self.channels:
            raise ValueError(f"expected L of shape [B,{self.channels},H,W], got {tuple(L.shape)}")

    def forward(self, L: torch.Tensor) -> torch.Tensor:
        """Gamma [B,C,1,1] in [g_min, g_max] for illumination maps ``L`` [B,C,H,W]."""
        self._check(L)
        if not self.per_view:  # one learned g for the scene: the same in every view
            z = self.out.bias.expand(L.shape[0], self.channels)
            return (self.g_min + (self.g_max - self.g_min) * torch.sigmoid(z))[:, :, None, None]
        x = L.to(self.out.weight.dtype)
        h, w = x.shape[-2:]
        scale = self.max_side / max(h, w)
        if scale < 1.0:
            size = (max(1, round(h * scale)), max(1, round(w * scale)))
            x = area_pool(x, size)  # area average: no aliasing of noisy maps
        logx = torch.log(x.clamp_min(self.eps_in)) / math.log(1.0 / self.eps_in)
        feat = self.features(torch.cat([x, logx], dim=1)).flatten(1)
        g = self.g_min + (self.g_max - self.g_min) * torch.sigmoid(self.out(feat))
        return g[:, :, None, None]
