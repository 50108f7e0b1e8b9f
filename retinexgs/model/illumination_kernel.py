"""The illumination field in training as two kernels and five matrix products (issue 65).

:class:`~retinexgs.model.illumination.IlluminationField` in torch is ~60 kernels a training step, forward and
backward: five Linear layers, the two positional encodings and their concatenations, the ReLUs, the view direction
and a column sum per bias (0.57 ms of GPU time at 58k Gaussians on an H200,
experiments/notes/2026-11-30-illumination-kernels.md). Here the forward is one kernel per Gaussian
(``csrc/include/rgs/illumination_train.h``, gaussian_colors.h's MLP keeping each layer's input), the backward one
kernel for every layer's output gradient and the centres' gradient, then one matrix product per layer for its weight
and bias gradients together (each layer's saved input carries a row of ones). The same values and gradients as the
torch field (tests/test_illumination_kernel.py, float64); it runs where the tone curve's kernels run (the GPU), the
CPU keeps torch (its numbers unchanged).
"""
from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from retinexgs.model.illumination import IlluminationField
from retinexgs.model.inference import fused_colors_unsupported, illumination_shape
from retinexgs.render._backend import kernels

__all__ = ["illumination_at", "kernels_apply", "kernels_unsupported"]

_LAYOUTS: Dict[Tuple[int, ...], Tuple[List[int], ...]] = {}


def _layout(shape: Tuple[int, ...]) -> Tuple[List[int], ...]:
    """(in, out, a_in, d_out, (a_width, d_width)) of the field's Linear layers in the kernels' buffers."""
    layout = _LAYOUTS.get(shape)
    if layout is None:
        layout = _LAYOUTS[shape] = tuple(list(v) for v in kernels().illumination_train_layout(list(shape)))
    return layout


def _linears(field: IlluminationField) -> List[nn.Linear]:
    """The field's Linear layers, trunk then head: the kernels' layer order."""
    return [m for m in field.trunk if isinstance(m, nn.Linear)] + [m for m in field.head if isinstance(m, nn.Linear)]


def kernels_unsupported(field: IlluminationField) -> Optional[str]:
    """Why the training kernels cannot run ``field`` (None when they can)."""
    why = fused_colors_unsupported(field)
    if why is None and len(_linears(field)) > 10:
        why = "the training kernels support a trunk of at most 8 Linear layers"
    return why


class _IlluminationKernels(torch.autograd.Function):
    """IlluminationField(means, view_dirs(means, center)) -> [N,3]; the parameters in :func:`_linears`' order
    (weight, bias per layer; the head's first weight as the forward uses it, ``head_weight()``)."""

    @staticmethod
    def forward(ctx, shape: Tuple[int, ...], bound: float, means: Tensor, center: Tensor, *params: Tensor) -> Tensor:
        weights = kernels().pack_illum_weights(list(params[0::2]), list(params[1::2]), *shape)
        rgb, A = kernels().illumination_forward(means, center, list(shape), bound, weights)
        ctx.shape, ctx.bound = shape, bound
        ctx.save_for_backward(means, center, weights, A, rgb)
        return rgb

    @staticmethod
    @once_differentiable
    def backward(ctx, g_rgb: Tensor):
        means, center, weights, A, rgb = ctx.saved_tensors
        g_means, D = kernels().illumination_backward(means, center, list(ctx.shape), ctx.bound, weights, A, rgb,
                                                     g_rgb.contiguous())
        ins, outs, a_in, d_out, _ = _layout(ctx.shape)
        chunk = int(kernels().illum_chunk)
        C = A.shape[1] // chunk  # the columns are whole chunks, the padding zero
        grads: List[Optional[Tensor]] = []
        for l, (n_in, n_out) in enumerate(zip(ins, outs)):
            # Σ over the Gaussians of [out] ⊗ [in + 1]: the weight's gradient, then the bias's (A's row of ones); one
            # product per chunk of Gaussians, then their sum
            d = D[d_out[l]:d_out[l] + n_out].view(n_out, C, chunk).transpose(0, 1)
            a = A[a_in[l]:a_in[l] + n_in + 1].view(n_in + 1, C, chunk).permute(1, 2, 0)
            g = torch.bmm(d, a).sum(0)
            grads += [g[:, :n_in], g[:, n_in]]
        return (None, None, g_means if ctx.needs_input_grad[2] else None, None, *grads)


def kernels_apply(field: IlluminationField, means: Tensor, center: Tensor) -> Tensor:
    """The field at ``means`` [N,3] seen from ``center`` (a [3] tensor on their device) through the training kernels,
    with autograd (the caller checks :func:`kernels_unsupported`)."""
    linears = _linears(field)
    params: List[Tensor] = []
    for i, m in enumerate(linears):
        params += [field.head_weight() if i == len(linears) - 2 else m.weight, m.bias]
    dtype = linears[0].weight.dtype
    return _IlluminationKernels.apply(tuple(illumination_shape(field)), field.bound, means.to(dtype),
                                      center.to(means.device, dtype).reshape(3), *params)


def illumination_at(field: IlluminationField, means: Tensor, center: Tensor) -> Tensor:
    """``field``'s illumination [N,3] at the Gaussians' centres seen from ``center``: through the training kernels on
    the GPU where they implement the field and a gradient is wanted, else torch's
    ``field(means, IlluminationField.view_dirs(means, center))`` (the CPU: its numbers stay torch's; without
    autograd the kernels' saved activations would be memory for nothing)."""
    if means.is_cuda and torch.is_grad_enabled() and kernels_unsupported(field) is None:
        return kernels_apply(field, means, center)
    return field(means, IlluminationField.view_dirs(means, center))
