"""L_enhance of the default configuration as a few kernels, its gradient carried forward (issue 65).

While ``loss.enhance_trains_scene`` is false R̂ and L̂ are detached in L_enhance's path, so the enhanced image
S_enh = srgb(s(k · lin(R̂∘L̂))) varies only with the tone's gain k (3 numbers, set by the EnhancementNet's g), and
L_spa, L_exp and L_col with it. ``csrc/include/rgs/enhance_loss.h`` computes the three terms and their 3×3 Jacobian in
k in one pass over the image and one over its 4×4 regions (on the GPU four launches over many blocks); the autograd
function here hands k its gradient from that Jacobian, and torch takes it on to g and the EnhancementNet. In torch the same terms are ~60 operators each way
(the tone curve, the pooling, the means and normalisations, the pair energy), about a sixth of a fox-dark step's
kernels while the enhancement is on. The torch composition (:func:`retinexgs.train.losses.enhancement_loss` on
:meth:`~retinexgs.model.retinex_model.RetinexGSModel.enhance`'s image) stays the reference the tests hold this to,
and the path for every other configuration.
"""
from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from retinexgs.config.schema import Loss
from retinexgs.model.tones import fused_curve
from retinexgs.render._backend import kernels
from retinexgs.train import losses

__all__ = ["applies", "enhancement_terms", "enhance_loss"]

POOL = 4  # L_spa's region size (losses.spatial_consistency_loss's default, as L_enhance calls it)


def applies(model, c: Loss, R_img: Tensor) -> bool:
    """Whether :func:`enhancement_terms` computes L_enhance for ``model`` under loss section ``c`` on the render's R̂
    ``R_img`` [H,W,3]: a tone that is a gain on the curve (the exposure tone), L_exp on the whole image, L_spa in
    Zero-DCE's form, R̂ and L̂ detached, on the device whose tone curve runs fused (the GPU), at any view size (the
    kernels took 0.71–0.78× the torch composition's time from 0.23 to 12 MP, experiments/enhance_loss_probe.py)."""
    return (fused_curve.runs_fused(R_img) and not c.enhance_trains_scene and model.tone.gain_curve
            and c.exp_on == "image" and c.exp_patch == 0 and c.exp_form in ("l2", "l1") and c.spa_form == "zero_dce"
            and R_img.dim() == 3 and R_img.shape[-1] == 3 and min(R_img.shape[:2]) >= POOL
            and R_img.dtype in (torch.float32, torch.float64))


class _EnhanceLoss(torch.autograd.Function):
    """(spa, exp, col) [3] of the image srgb(s(k · lin(x))) against the view ``s``; differentiable in ``k`` only."""

    @staticmethod
    def forward(ctx, x: Tensor, s: Tensor, k: Tensor, E: Tensor, knee: float, exp_l1: bool,
                scale_invariant: bool) -> Tensor:
        out = kernels().enhance_loss(x, s, k.reshape(3), E, POOL, knee, fused_curve.FORMS["clip"],
                                     fused_curve.FORMS["clip"], exp_l1, scale_invariant)
        ctx.k_shape = k.shape
        ctx.save_for_backward(out[3:].view(3, 3))
        return out[:3]

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        (jacobian,) = ctx.saved_tensors  # [term, channel]
        return None, None, (grad @ jacobian).reshape(ctx.k_shape), None, None, None, None


def enhance_loss(x: Tensor, s: Tensor, k: Tensor, E: Tensor, knee: float, exp_l1: bool = False,
                 scale_invariant: bool = True) -> Tensor:
    """L_spa, L_exp, L_col [3] (unweighted) of S_enh = srgb(s_knee(k · lin(x))) against ``s`` (both [H,W,3], H and W
    at least 4), E a one-element tensor; a gradient reaches ``k`` ([3]) alone."""
    return _EnhanceLoss.apply(x.contiguous(), s.contiguous(), k, E.reshape(1).to(x), float(knee), bool(exp_l1),
                              bool(scale_invariant))


def enhancement_terms(model, c: Loss, R_img: Tensor, L_img: Tensor, S_b: Tensor
                      ) -> Tuple[Tensor, Dict[str, Tensor]]:
    """What :func:`retinexgs.train.objective.enhancement_objective` returns, where :func:`applies`: L_enhance's
    weighted sum and its terms (``exp_E`` logged beside them) for the detached [H,W,3] maps R̂, L̂ and the view
    ``S_b`` [1,3,H,W]."""
    g = model.enhance_gamma(L_img)
    k = model.tone.fused_gain(model.illum_ref, g)
    RL = R_img * L_img
    E = losses.exposure_target(c, model.tone, RL, model.shoulder)
    E_t = E.detach().reshape(1) if torch.is_tensor(E) else RL.new_full((1,), float(E))
    values = enhance_loss(RL, S_b[0].permute(1, 2, 0), k, E_t, float(model.shoulder), c.exp_form == "l1",
                          bool(c.enhance_scale_invariant))
    terms: Dict[str, Tensor] = dict(zip(("spa", "exp", "col"), values.unbind()))
    total: Optional[Tensor] = None
    for name, weight in (("spa", c.w_spa), ("exp", c.w_exp), ("col", c.w_col)):
        if weight:
            total = weight * terms[name] if total is None else total + weight * terms[name]
    terms["exp_E"] = E_t.float().reshape(())  # logged, not a loss (as enhancement_objective's)
    return (RL.new_zeros(()) if total is None else total), terms
