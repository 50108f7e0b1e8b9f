"""The implicit 3D illumination field of RetinexGS (paper Sec. II.C, Fig. 3).

An MLP maps a positionally-encoded 3D position ``x`` and a positionally-encoded viewing direction ``d``
to an RGB illumination value. It is evaluated once per Gaussian for the current camera (position = the
Gaussian's centre, direction = unit vector from the camera centre to it); the rasterizer then splats
these values like colours to give the illumination map L̂, and S ≈ R̂ ∘ L̂ (paper Eq. 2, 4).

Architecture. The paper's text says only "an MLP on positionally encoded x and d -> RGB" and that Fig. 3
labels the feature widths; the figure itself is not in our copy, so the widths here are our choice
(all configurable):

    PE(x)  [3 + 6·L_x = 63]  -> (Linear(hidden) + ReLU) × depth  -> feature [hidden=64]
    concat(feature, PE(d) [3 + 6·L_d = 27])  -> Linear(dir_hidden=32) + ReLU -> Linear(3) -> sigmoid

Position enters the trunk only and direction only the head (NeRF style), so view dependence stays a
small correction on a spatially smooth field. ``view_dependent=False`` removes it: the head's direction
columns are held at zero, so L̂ is a function of position alone. Why: in Retinex the illumination is the light
arriving at a point, the same from every viewpoint; what a viewpoint changes (gloss) belongs to the
reflectance's SH. A direction input lets L̂ fit each view's own noise and exposure, and on a view past the
training views it extrapolates freely. Held at zero (not removed), the layer keeps the layout the fused
colour kernel evaluates, which then gives the same values for any direction.

Input scaling. Positions are expected in the loader's normalised world (train cameras in the unit ball,
scene content roughly within [-1.5, 1.5]). They are divided by ``bound`` (default 2.0) before encoding
so that the lowest frequency sin(π·x/bound) has a period (2·bound) longer than the scene and stays
unambiguous; points beyond ``bound`` are still valid inputs (the encoding is periodic, nothing is
clamped). Directions are normalised to unit length inside :meth:`IlluminationField.forward`.
Encoding frequencies are 2^k·π for k = 0..L-1 and the raw input is included.

Output activation: a sigmoid, so L̂ ∈ (0, 1). Reasons: the 2D targets L from the decomposer lie in
(0, 1]; the enhancement L_enh = L̂^g (Eq. after 6) with g ∈ (0, 1] then also stays ≤ 1, so S_enh never
exceeds R̂; and, unlike exp/softplus, it cannot blow up. In the dark regime (L ~ 0.02–0.3) the sigmoid
behaves like exp (dσ/dz = σ(1−σ) ≈ σ), i.e. it learns in log-space, which suits multiplicative
illumination. The last layer's bias starts at logit(``init_value``) (default 0.1, a typical dark-scene
illumination) with small weights, so training starts near the right level instead of at 0.5.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["positional_encoding", "encoded_dim", "IlluminationField"]


def encoded_dim(in_dim: int, n_freqs: int, include_input: bool = True) -> int:
    """Width of :func:`positional_encoding`'s output for an ``in_dim``-wide input."""
    return in_dim * (2 * n_freqs + (1 if include_input else 0))


_FREQS: dict = {}  # (n_freqs, dtype, device) -> [n_freqs] 2^k·π


def positional_encoding(x: torch.Tensor, n_freqs: int, include_input: bool = True) -> torch.Tensor:
    """NeRF positional encoding γ(x) = (x, sin(2^k π x), cos(2^k π x))_{k<n_freqs}.

    Args:
        x: [..., D] input.
        n_freqs: number of octaves L (frequencies 2^0 π … 2^(L-1) π).
        include_input: prepend the raw input.

    Returns:
        [..., D·(2L + include_input)]: raw input first, then all sines, then all cosines.
    """
    if n_freqs <= 0:
        return x if include_input else x[..., :0]
    key = (n_freqs, x.dtype, x.device)
    freqs = _FREQS.get(key)
    if freqs is None:  # built once per (L, dtype, device): 3 kernels fewer per call in the training loop
        freqs = _FREQS[key] = (2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)) * math.pi
    xb = (x[..., None, :] * freqs[:, None]).flatten(-2)  # [..., L·D]
    parts = [x] if include_input else []
    parts += [torch.sin(xb), torch.cos(xb)]
    return torch.cat(parts, dim=-1)


class IlluminationField(nn.Module):
    """MLP (PE(x), PE(d)) -> RGB illumination in (0, 1); see the module docstring.

    Args:
        pos_freqs: L_x, octaves for position (paper/NeRF default 10).
        dir_freqs: L_d, octaves for direction (default 4).
        hidden: width of the position trunk.
        depth: number of hidden layers in the position trunk (≥ 1).
        dir_hidden: width of the direction head's hidden layer.
        bound: positions are divided by this before encoding (see "Input scaling").
        init_value: initial output for every input (sigmoid bias = logit(init_value)).
        view_dependent: False holds the head's direction columns at zero (see the module docstring).
    """

    def __init__(self, pos_freqs: int = 10, dir_freqs: int = 4, hidden: int = 64, depth: int = 3,
                 dir_hidden: int = 32, bound: float = 2.0, init_value: float = 0.1,
                 view_dependent: bool = True) -> None:
        super().__init__()
        if depth < 1:
            raise ValueError("depth must be >= 1")
        if not 0.0 < init_value < 1.0:
            raise ValueError("init_value must be in (0, 1)")
        if bound <= 0:
            raise ValueError("bound must be > 0")
        self.pos_freqs, self.dir_freqs, self.bound = int(pos_freqs), int(dir_freqs), float(bound)

        layers = []
        width = encoded_dim(3, self.pos_freqs)
        for _ in range(depth):
            layers += [nn.Linear(width, hidden), nn.ReLU(inplace=True)]
            width = hidden
        self.trunk = nn.Sequential(*layers)
        self.head = nn.Sequential(
            nn.Linear(hidden + encoded_dim(3, self.dir_freqs), dir_hidden), nn.ReLU(inplace=True),
            nn.Linear(dir_hidden, 3))
        self.view_dependent = bool(view_dependent)
        # 1 on the feature columns of the head's first layer, 0 on the direction columns (all 1 when view
        # dependent). Not persistent: it follows from the config, and older checkpoints lack it.
        mask = torch.ones(1, hidden + encoded_dim(3, self.dir_freqs))
        if not self.view_dependent:
            mask[:, hidden:] = 0.0
            with torch.no_grad():
                self.head[0].weight.mul_(mask)
        self.register_buffer("head_mask", mask, persistent=False)
        out = self.head[-1]
        # Small last-layer weights: the field starts ~constant at init_value but still gets gradients.
        nn.init.uniform_(out.weight, -1e-3, 1e-3)
        nn.init.constant_(out.bias, math.log(init_value / (1.0 - init_value)))

    def forward(self, xyz: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """Illumination at ``xyz`` [N,3] seen along ``dirs`` [N,3] (any length, not all zero) -> [N,3] in (0,1)."""
        if xyz.shape[-1] != 3 or dirs.shape[-1] != 3 or xyz.shape[:-1] != dirs.shape[:-1]:
            raise ValueError(f"expected xyz and dirs of shape [N,3], got {tuple(xyz.shape)} "
                             f"and {tuple(dirs.shape)}")
        dtype = self.trunk[0].weight.dtype
        x = xyz.to(dtype) / self.bound
        d = F.normalize(dirs.to(dtype), dim=-1, eps=1e-12)
        feat = self.trunk(positional_encoding(x, self.pos_freqs))
        h = torch.cat([feat, positional_encoding(d, self.dir_freqs)], dim=-1)
        # The masked weight gets a zero gradient on the direction columns: Adam leaves them at zero.
        h = F.linear(h, self.head_weight(), self.head[0].bias)
        h = F.relu(h)
        return torch.sigmoid(self.head[-1](h))

    def head_weight(self) -> torch.Tensor:
        """The weight of the head's first layer as the forward uses it (direction columns zeroed when not view
        dependent): what the fused colour kernel must be given."""
        w = self.head[0].weight
        return w if self.view_dependent else w * self.head_mask

    @staticmethod
    def view_dirs(xyz: torch.Tensor, camera_center: torch.Tensor) -> torch.Tensor:
        """Unit directions from ``camera_center`` [3] to each point of ``xyz`` [N,3] (the trainer's input)."""
        return F.normalize(xyz - camera_center.to(xyz).reshape(1, 3), dim=-1, eps=1e-12)
