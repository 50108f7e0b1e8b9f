"""Unit quaternions to rotation matrices, for the product and its pure-torch twin alike."""
from __future__ import annotations

import torch
from torch import Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] (w, x, y, z) -> [N, 3, 3]; a zero quaternion gives the identity."""
    n = quats.norm(dim=-1, keepdim=True)
    q = torch.where(n > 1e-12, quats / n.clamp_min(1e-12), torch.zeros_like(quats))
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)
