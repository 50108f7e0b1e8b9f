"""White balance of the photos before training (``data.white_balance``, issue 53's training-time ablation).

``as-shot`` (the default) trains on the photos as the camera balanced them. ``grey-edge`` estimates one set of
gains for the whole capture from its training photos and applies it to every view's photo (train, test and val;
never to the normal-light truth) in linear light, before the 2D priors, the noise estimates and the training
targets see them: a camera's auto white balance, done once per scene.

The estimator is grey-edge (van de Weijer, Gevers & Gijsenij 2007; first order, Minkowski norm 1), the same as
``render --white-balance auto``: the mean gradient magnitude of each channel of the linear light is taken to be
achromatic. On a dark photo the noise's gradients would dominate, so each photo is first averaged over 4×4 blocks
in linear light (the noise's σ falls 4×; the scene's edges stay). Deterministic: float64 sums in a fixed order over
at most :data:`MAX_VIEWS` training photos, evenly spaced.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable, Optional, Sequence, Tuple

import torch

from retinexgs.data.images import load_image_tensor
from retinexgs.data.srgb import linear_to_srgb, linear_to_srgb_extended, srgb_to_linear_extended
from retinexgs.errors import UserError

__all__ = ["BALANCES", "MAX_VIEWS", "BLOCK", "grey_edge_light", "estimate_photo_balance", "balance_photo",
           "describe_photo_balance"]

BALANCES = ("as-shot", "grey-edge")
MAX_VIEWS = 32  # photos the estimate reads (evenly spaced): bounded time on captures of thousands
BLOCK = 4  # the block mean before the gradients: a dark photo's noise would otherwise be the "edges"

Gains = Tuple[float, float, float]


def grey_edge_light(images: Iterable[torch.Tensor]) -> Tuple[float, float, float]:
    """The light's colour by grey-edge: per channel the mean over all pixels of all ``images`` (linear [H,W,3],
    H, W ≥ 2) of the gradient magnitude (forward differences), summed in float64 in a fixed order. (0, 0, 0)
    when there are no pixels."""
    total = torch.zeros(3, dtype=torch.float64)
    count = 0
    for img in images:
        x = img.detach().double().cpu()
        dx = x[:-1, 1:] - x[:-1, :-1]
        dy = x[1:, :-1] - x[:-1, :-1]
        mag = (dx * dx + dy * dy).sqrt()
        total += mag.reshape(-1, 3).sum(0)
        count += mag.shape[0] * mag.shape[1]
    e = (total / max(count, 1)).tolist()
    return e[0], e[1], e[2]


def _blocks(light: torch.Tensor, block: int) -> torch.Tensor:
    h, w = light.shape[0] // block * block, light.shape[1] // block * block
    if h < 2 * block or w < 2 * block:  # too small to average: the photo as it is
        return light
    return light[:h, :w].reshape(h // block, block, w // block, block, 3).mean(dim=(1, 3))


def estimate_photo_balance(paths: Sequence[Path], block: int = BLOCK) -> Gains:
    """Grey-edge gains (G/R, 1, G/B) of a capture's photos (module docstring): the photos' unclipped values where
    they have them (camera raw), in linear light, averaged over ``block`` × ``block`` pixels. UserError when the
    photos have no edges in some channel (black or flat photos)."""
    if not paths:
        raise UserError("data.white_balance grey-edge: the scene has no training photos to estimate it from")
    step = max(1, -(-len(paths) // MAX_VIEWS))
    chosen = list(paths)[::step]
    e = grey_edge_light(_blocks(srgb_to_linear_extended(load_image_tensor(p, unclipped=True).double()), block)
                        for p in chosen)
    if min(e) <= 1e-12:
        raise UserError("data.white_balance grey-edge: the training photos have no edges in some channel (black or "
                        "flat photos), so no white balance can be estimated from them; use data.white_balance as-shot")
    return (e[1] / e[0], 1.0, e[1] / e[2])


def balance_photo(image: torch.Tensor, gains: Optional[Sequence[float]], unclipped: bool = False) -> torch.Tensor:
    """A photo [H,W,3] (sRGB-encoded; with ``unclipped`` the extended encoding of a raw view's values) with
    ``gains`` applied to its linear light; the same encoding back (clipped to [0, 1] unless ``unclipped``).
    None: the photo itself."""
    if gains is None:
        return image
    g = torch.tensor(list(gains), dtype=torch.float64)
    light = srgb_to_linear_extended(image.double()) * g
    out = linear_to_srgb_extended(light) if unclipped else linear_to_srgb(light.clamp(0.0, 1.0))
    return out.to(image.dtype)


def describe_photo_balance(gains: Optional[Sequence[float]]) -> str:
    """One line for the training log."""
    if gains is None:
        return "photos' white balance: as shot"
    return ("photos' white balance: grey-edge (data.white_balance), gains R,G,B = "
            + ", ".join(f"{v:.4g}" for v in gains) + " in linear light, on every view's photo (not the truth)")
