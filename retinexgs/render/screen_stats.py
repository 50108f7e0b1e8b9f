"""Densification's screen-space statistics of one view, added in place after the backward (3DGS, Kerbl et al.
2023, §5.2): for each Gaussian seen in the view (both pixel radii > 0) the norm of its projected centre's gradient
in NDC units and one more view that saw it, and for every Gaussian the running maximum of its pixel radius.

One fused kernel (``csrc/include/rgs/screen_stats.h``) instead of the ~9 elementwise kernels of the torch form,
which the tests hold it to (:func:`screen_stats_reference`): a training step is launch-bound (issue 65: the torch
form was 0.26 ms of a 4.5 ms fox-dark step).
"""
from __future__ import annotations

import torch
from torch import Tensor

from retinexgs.render._backend import kernels


def screen_stats(grad2d: Tensor, radii: Tensor, width: int, height: int, grad_accum: Tensor, count: Tensor,
                 max_radius: Tensor) -> None:
    """Add one view's statistics to ``grad_accum``, ``count`` and ``max_radius`` ([N] float32, contiguous, on
    ``grad2d``'s device) in place. ``grad2d``: [N, 2] pixel gradients of the projected centres; ``radii``: [N, 2]
    int32 (0: culled); ``width``, ``height``: the view's size in pixels (NDC = pixels / (size / 2))."""
    kernels().screen_stats(grad2d.detach(), radii, width / 2.0, height / 2.0, grad_accum, count, max_radius)


def screen_stats_reference(grad2d: Tensor, radii: Tensor, width: int, height: int, grad_accum: Tensor,
                           count: Tensor, max_radius: Tensor) -> None:
    """The pure-torch twin of :func:`screen_stats` (the tests' reference)."""
    scale = torch.tensor([width / 2.0, height / 2.0], device=grad2d.device, dtype=grad2d.dtype)
    norm = (grad2d.detach() * scale).norm(dim=-1).float()
    visible = (radii > 0).all(dim=-1)
    grad_accum += torch.where(visible, norm, 0.0)
    count += visible
    torch.maximum(max_radius, radii.amax(dim=-1), out=max_radius)
