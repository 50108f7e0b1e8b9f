"""The tone curve training runs every step, as one kernel each way: y = srgb_o(s(k · lin_i(x))) elementwise.

The exposure tone's S_enh and L_enh (:mod:`.exposure`), the reconstruction's exposed photos
(:func:`retinexgs.train.losses.exposed`) and a raw view's linear light are all this chain with different clips. In
torch it is ~12 elementwise operators forward and as many backward, each a full pass over the image: at 12 MP a
training step is bound by those bytes (issue 65,
experiments/notes/2026-11-29-redenoise-gpu-step-launches.md §5). :func:`tone_curve` runs it as one kernel
(``csrc/include/rgs/tone_curve.h``, CPU and CUDA; used on the GPU) with an analytic backward; :func:`tone_curve_reference` is its
pure-torch twin, the composition of :mod:`retinexgs.data.srgb`'s curves and the shoulder, which the tests hold it to.

Forms of the input's curve lin_i: ``clip`` (x clamped to [0, 1] first), ``open`` (clamped at 0 only: light past
white keeps rising), ``extended`` (no clamp: a raw view's encoding); of the output's: the same three, or ``linear``
(no sRGB curve: the light s(k · lin_i(x)) itself).
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from retinexgs.data.srgb import linear_to_srgb, linear_to_srgb_extended, srgb_to_linear, srgb_to_linear_extended
from retinexgs.model.tones.curves import highlight_shoulder
from retinexgs.render._backend import kernels

__all__ = ["FORMS", "tone_curve", "tone_curve_kernel", "tone_curve_reference", "to_linear", "runs_fused"]

FORMS = {"clip": 0, "open": 1, "extended": 2, "linear": 3}


def _form(name: str, output: bool) -> int:
    code = FORMS.get(name)
    if code is None or (code == FORMS["linear"] and not output):
        choices = ", ".join(n for n in FORMS if output or n != "linear")
        raise ValueError(f"tone curve form must be one of {choices}, got {name!r}")
    return code


def _gain_layout(x: Tensor, gain: Tensor) -> Optional[Tuple[int, int]]:
    """(C, inner) such that element i of contiguous ``x`` takes gain[(i // inner) % C], or None where ``gain`` does
    not broadcast that way (more than one axis, or it would enlarge ``x``): the caller falls back to the twin."""
    if gain.dim() > x.dim():
        return None
    shape = (1,) * (x.dim() - gain.dim()) + tuple(gain.shape)
    axes = [d for d, s in enumerate(shape) if s != 1]
    if not axes:
        return 1, 1
    if len(axes) > 1 or shape[axes[0]] != x.shape[axes[0]]:
        return None
    d = axes[0]
    return int(x.shape[d]), math.prod(x.shape[d + 1:])


class _ToneCurve(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, gain: Tensor, knee: float, form_in: int, form_out: int, C: int, inner: int):
        x = x.contiguous()
        k = gain.reshape(-1).contiguous()
        ctx.meta = (knee, form_in, form_out, C, inner, gain.shape)
        ctx.save_for_backward(x, k)
        return kernels().tone_curve_forward(x, k, C, inner, knee, form_in, form_out)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        x, k = ctx.saved_tensors
        knee, form_in, form_out, C, inner, gain_shape = ctx.meta
        need_x, need_gain = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        gx, gk = kernels().tone_curve_backward(x, k, grad.contiguous(), C, inner, knee, form_in, form_out,
                                               need_x, need_gain)
        # The gain's gradient summed per channel by torch: one order, so the result is deterministic.
        return (gx if need_x else None, gk.sum_to_size(gain_shape) if need_gain else None,
                None, None, None, None, None)


def tone_curve(x: Tensor, gain: Tensor, knee: float = 1.0, form_in: str = "clip", form_out: str = "clip") -> Tensor:
    """srgb_o(s(gain · lin_i(x))) of ``x`` (any shape; float32/64), differentiable in ``x`` and ``gain``.

    ``gain``: a tensor broadcastable against ``x`` (one value, or varying along one axis: a per-channel gain);
    ``knee``: the highlight shoulder's (:func:`~retinexgs.model.tones.curves.highlight_shoulder`; >= 1: none);
    ``form_in``/``form_out``: the curves' clips (module docstring). On the GPU one fused kernel each way
    (:func:`tone_curve_kernel`); on the CPU the twin, whose vectorised torch operators beat the kernel's scalar
    loop there (0.11–0.16 s against 0.21–0.40 s forward + backward at 1024×768×3 on 2 cores, 2026-11-29) and which
    keeps CPU training exactly as it was."""
    if runs_fused(x):
        return tone_curve_kernel(x, gain, knee, form_in, form_out)
    return tone_curve_reference(x, gain, knee, form_in, form_out)


def runs_fused(x: Tensor) -> bool:
    """Whether :func:`tone_curve` takes the kernel for ``x`` (on the GPU; ``scripts/profiling.py ops --fused-curves``
    sets it true everywhere, so that a CPU census counts what the GPU runs)."""
    return x.is_cuda


def tone_curve_kernel(x: Tensor, gain: Tensor, knee: float = 1.0, form_in: str = "clip",
                      form_out: str = "clip") -> Tensor:
    """:func:`tone_curve` through the fused kernel on either device (the CPU's is the reference the CUDA one is
    tested against); a gain of another layout, dtype or device takes :func:`tone_curve_reference`, the same values."""
    fi, fo = _form(form_in, False), _form(form_out, True)
    layout = _gain_layout(x, gain)
    if layout is None or gain.dtype != x.dtype or gain.device != x.device:
        return tone_curve_reference(x, gain, knee, form_in, form_out)
    return _ToneCurve.apply(x, gain, float(knee), fi, fo, *layout)


def tone_curve_reference(x: Tensor, gain: Tensor, knee: float = 1.0, form_in: str = "clip",
                         form_out: str = "clip") -> Tensor:
    """The pure-torch twin of :func:`tone_curve` (the tests' reference; the curves of :mod:`retinexgs.data.srgb`)."""
    _form(form_in, False), _form(form_out, True)
    lin = srgb_to_linear_extended(x) if form_in == "extended" else srgb_to_linear(x, clip=form_in == "clip")
    v = highlight_shoulder(gain * lin, knee)
    if form_out == "linear":
        return v
    return linear_to_srgb_extended(v) if form_out == "extended" else linear_to_srgb(v, clip=form_out == "clip")


def to_linear(x: Tensor, form: str = "open") -> Tensor:
    """lin_i(x), the linear light of sRGB-encoded ``x`` under the input form ``form``: :func:`tone_curve` at gain
    1 with a linear output (one kernel each way where :func:`retinexgs.data.srgb.srgb_to_linear` is ~8)."""
    return tone_curve(x, x.new_ones(()), 1.0, form, "linear")
