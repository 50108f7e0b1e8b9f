"""Synthetic benchmark scenes: random Gaussians in a cube seen by a camera on a circle around it."""
from __future__ import annotations

import math
from typing import Dict

import torch

from retinexgs.render import Camera


def orbit_camera(width: int, height: int, fov_x_deg: float = 60.0, radius: float = 3.0,
                 angle: float = 0.0) -> Camera:
    """An OpenCV camera at distance ``radius`` from the origin, looking at it."""
    eye = torch.tensor([radius * math.sin(angle), -0.3 * radius, -radius * math.cos(angle)], dtype=torch.float64)
    z = -eye / eye.norm()
    x = torch.linalg.cross(z, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = torch.stack([x, y, z])
    vm[:3, 3] = -vm[:3, :3] @ eye
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return Camera(vm, f, f, width / 2, height / 2, width, height)


def random_scene(n: int, sh_degree: int = 3, seed: int = 0, device: str = "cpu",
                 dtype: torch.dtype = torch.float32) -> Dict[str, torch.Tensor]:
    """n Gaussians uniform in [-1, 1]³, scales log-uniform in [0.003, 0.03] x (100k / n)^(1/3) so that
    coverage stays comparable across n, opacities uniform in [0.05, 0.95], SH coefficients ~ N(0, 0.3)."""
    g = torch.Generator().manual_seed(seed)
    size = (1e5 / n) ** (1 / 3)
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.003), math.log(0.03), generator=g)) * size
    scene = {
        "means": torch.rand(n, 3, generator=g) * 2 - 1,
        "quats": torch.randn(n, 4, generator=g),
        "scales": scales,
        "opacities": torch.rand(n, generator=g) * 0.9 + 0.05,
        "sh": torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.3,
    }
    return {k: v.to(device=device, dtype=dtype) for k, v in scene.items()}
