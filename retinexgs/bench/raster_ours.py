"""Our rasterizer as the raster benchmarks call it (shared by the CPU and the CUDA benchmark)."""
from __future__ import annotations

from typing import Dict

import torch

from retinexgs.render import Camera, rasterize_gaussians, spherical_harmonics


def render_ours(scene: Dict[str, torch.Tensor], cam: Camera, degree: int, validate: bool = True) -> torch.Tensor:
    """Our render of ``scene``; ``validate=False`` skips the public API's NaN/inf check (done inside the
    projection kernel, read at binning's sync), as the trainer and the frame renderer do."""
    dirs = scene["means"] - cam.center.to(scene["means"])
    colors = torch.clamp_min(spherical_harmonics(degree, dirs, scene["sh"]) + 0.5, 0.0)
    return rasterize_gaussians(scene["means"], scene["quats"], scene["scales"], scene["opacities"], colors,
                               cam, validate=validate).image


def render_ours_unchecked(scene: Dict[str, torch.Tensor], cam: Camera, degree: int) -> torch.Tensor:
    """:func:`render_ours` without the input check."""
    return render_ours(scene, cam, degree, validate=False)
