"""The training loss's SSIM on the fused kernels (``csrc/include/rgs/ssim.h``): Gaussian window, zero ("same")
padding, the gradient with respect to the render only (the other image is the fixed target).

Two kernels a call each way instead of two depthwise convolutions and ~20 elementwise ones (issue 65: SSIM's
filters were 0.74 ms of a 4.75 ms fox-dark step, and ~40 % of a 12 MP step). The pure-torch twin, which the tests
hold it to, is :func:`retinexgs.evaluate.metrics.ssim` with ``padding="same"``.
"""
from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from retinexgs.render._backend import kernels


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, y: Tensor, window: Tensor, c1: float, c2: float) -> Tensor:
        s, partials = kernels().ssim_forward(x, y, window, c1, c2, ctx.needs_input_grad[0])
        ctx.save_for_backward(x, y, partials, window)
        return s

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        x, y, partials, window = ctx.saved_tensors
        return kernels().ssim_backward(grad, x, y, partials, window), None, None, None, None


def fused_ssim_map(x: Tensor, y: Tensor, window: Tensor, c1: float, c2: float) -> Tensor:
    """The SSIM map of ``x`` against ``y`` ([..., H, W], one dtype and device), per plane, with the 1-D window
    ``window`` (odd, ≤ 15 taps) applied along both axes over zero padding and the constants c1, c2.

    Differentiable in ``x`` only: raises ValueError where ``y`` requires a gradient (use the torch twin there)."""
    if y.requires_grad:
        raise ValueError("fused_ssim_map differentiates x only; y requires a gradient (use evaluate.metrics.ssim)")
    return _FusedSSIM.apply(x, y, window, float(c1), float(c2))
