"""RetinexGS's per-pixel image losses as one kernel each way (``csrc/include/rgs/supervision.h``, issue 65): the
2D priors' supervision and the reconstruction of Eq. 4 (its L1 parts; the SSIM parts on the fused SSIM), L_TV
(Eq. 5) and the depth prior's smoothness, from the loss graph's inputs as they are: the render [H,W,6|8] and the
view's packed targets [H,W,7|9].

In torch these terms are ~200 small kernels a step inside the loss graph that move ~2.5 kB a pixel (the CPU census
of ``scripts/profiling.py ops --traffic``): each costs its launch at 360×640 and its bytes at 12 MP. The values are
those of :func:`retinexgs.train.losses.supervision_loss`, :func:`~retinexgs.train.losses.tv_loss` and
:func:`~retinexgs.train.losses.depth_smoothness_loss`, their pure-torch twins, which the tests hold it to (values and
gradients, float64); :func:`plan` says which configurations it covers, the rest take the twins. It runs where the
tone curve's kernel runs (``fused_curve.runs_fused``: the GPU). On the CPU the twins stay: their vectorised operators
beat the kernel's scalar loop there (forward + backward at 640×480, float32, 2 threads: 0.18–0.20 s against
0.21–0.25 s, 2026-11-29), and CPU training keeps its numbers bit for bit.
"""
from __future__ import annotations

from typing import Dict, NamedTuple, Optional, Tuple, Union

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from retinexgs.evaluate.metrics import cached_constant
from retinexgs.render._backend import kernels
from retinexgs.model.tones.fused_curve import FORMS
from retinexgs.train.losses import (DEPTH_EPS, DEPTH_MIN_ALPHA, RELATIVE_EPS, LinearTarget, prior_confidence,
                                    ssim_map, to_bchw)

__all__ = ["Supervision", "plan", "supervision_terms", "REC_FORMS"]

# rgs::RecForm and rgs::SupervisionSum
REC_FORMS = {"plain": 0, "exposed": 1, "noise": 2, "relative": 3}
(SUM_R, SUM_L, SUM_REC, SUM_W, SUM_TVX, SUM_TVY, SUM_DISP, SUM_COV, SUM_DX, SUM_MX, SUM_DY, SUM_MY) = range(12)


class Supervision(NamedTuple):
    """What the pass computes, besides the render and the targets: ``rec_form`` (REC_FORMS), ``ssim_gain`` (the SSIM
    pair's exposure, a [1] tensor, or None: R̂∘L̂ and S as they are), ``lin_gain`` (the exposed L1's or the linear
    term's gain), a raw view's noise ``a``, ``b`` ([3]), ``extended`` (S is a raw view's unclipped encoding), ``r_luma``
    (``loss.raw.r_prior_luma`` on a raw scene: the share of R̂'s luma the R prior compares)."""
    rec_form: int
    ssim_gain: Optional[Tensor] = None
    lin_gain: Optional[Tensor] = None
    a: Optional[Tensor] = None
    b: Optional[Tensor] = None
    extended: bool = False
    r_luma: float = 1.0


def _three(t: Tensor, like: Tensor) -> Tensor:
    """A per-channel noise coefficient ([1,3,1,1] or one value) as [3] in ``like``'s dtype."""
    return torch.broadcast_to(t.reshape(-1), (3,)).to(like.dtype).contiguous()


def plan(rec_gain: Optional[Tensor], l1_exposed: bool, linear: Optional[LinearTarget], like: Tensor,
         r_luma: float = 1.0) -> Optional[Supervision]:
    """The pass's :class:`Supervision` for :func:`retinexgs.train.losses.supervision_loss`'s options (``rec_gain``,
    ``rec_l1_exposed``, ``linear``, ``r_luma``) on a render like ``like``, or None where the pass does not cover
    them: a linear term of unit ``sigma``, or a gain that needs a gradient (the twins run then)."""
    gains = [t for t in (rec_gain, None if linear is None else linear.gain) if t is not None]
    if any(t.requires_grad or t.numel() != 1 for t in gains):
        return None

    def one(t: Optional[Tensor]) -> Optional[Tensor]:
        return None if t is None else t.reshape(1).to(like.dtype)

    if linear is None:
        exposed = rec_gain is not None and l1_exposed
        return Supervision(REC_FORMS["exposed" if exposed else "plain"], one(rec_gain),
                           one(rec_gain) if exposed else None, r_luma=r_luma)
    if linear.unit != "plain" or linear.mode not in ("noise", "relative"):
        return None
    g = linear.gain if linear.gain is not None else rec_gain
    return Supervision(REC_FORMS[linear.mode], one(rec_gain), one(g) if g is not None else like.new_ones(1),
                       _three(linear.a, like), _three(linear.b, like), extended=True, r_luma=r_luma)


class _SupervisionPass(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image: Tensor, packed: Tensor, conf: Optional[Tensor], sup: Supervision):
        args = (sup.ssim_gain, sup.lin_gain, sup.a, sup.b, conf)
        s_form = FORMS["extended" if sup.extended else "open"]
        x9, y9, partials = kernels().supervision_forward(image, packed, *args, sup.rec_form, s_form, RELATIVE_EPS,
                                                         DEPTH_MIN_ALPHA, DEPTH_EPS, sup.r_luma)
        ctx.mark_non_differentiable(y9)
        ctx.meta = (args, sup.rec_form, s_form, sup.r_luma)
        ctx.save_for_backward(image, packed)
        return x9, y9, partials.sum(0)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_x9: Optional[Tensor], _g_y9: Optional[Tensor], g_sums: Optional[Tensor]):
        image, packed = ctx.saved_tensors
        args, rec_form, s_form, r_luma = ctx.meta
        if g_sums is None:
            g_sums = image.new_zeros(12)
        grad = kernels().supervision_backward(image, packed, *args, g_x9, g_sums, rec_form, s_form, RELATIVE_EPS,
                                              DEPTH_MIN_ALPHA, DEPTH_EPS, r_luma)
        return grad, None, None, None


def _sum_scales(H: int, W: int, noise: bool, dtype: torch.dtype, device: torch.device) -> Tuple[Tensor, Tensor]:
    """([4,12]: the pass's sums to the L1 means of sup_r, sup_l, sup_rec and L_TV; [12]: the sums the noise forms
    divide by the weights' sum, the reconstruction's) for an H×W view."""
    def build() -> Tuple[Tensor, Tensor]:
        means = torch.zeros(4, 12, dtype=dtype, device=device)
        n = 3.0 * H * W
        means[0, SUM_R], means[1, SUM_L], means[2, SUM_REC] = 1.0 / n, 1.0 / n, 1.0 if noise else 1.0 / n
        if W > 1:
            means[3, SUM_TVX] = 1.0 / (3.0 * H * (W - 1))
        if H > 1:
            means[3, SUM_TVY] = 1.0 / (3.0 * (H - 1) * W)
        over = torch.zeros(12, dtype=torch.bool, device=device)
        over[SUM_REC] = noise
        return means, over
    return cached_constant(("supervision_scales", H, W, noise, dtype, device), build)


def _weights(weights: Union[Tuple[float, float, float], Tensor], dtype: torch.dtype, device: torch.device
             ) -> Tensor:
    """(w_r, w_l, w_s) as a [3] tensor (floats: built once; a tensor, the objective's scheduled weights, as is)."""
    if isinstance(weights, Tensor):
        return weights.to(dtype)
    key = ("supervision_weights", tuple(float(w) for w in weights), dtype, device)
    return cached_constant(key, lambda: torch.tensor(key[1], dtype=dtype, device=device))


def supervision_terms(image: Tensor, packed: Tensor, sup: Supervision,
                      weights: Union[Tuple[float, float, float], Tensor],
                      lambda_ssim: float, linear: Optional[LinearTarget] = None
                      ) -> Tuple[Tensor, Dict[str, Tensor]]:
    """(w_r·sup_r + w_l·sup_l + w_s·sup_rec, {"sup_r", "sup_l", "sup_rec", "tv"[, "depth"]}) of the render ``image``
    [H,W,6] (R̂, L̂) or [H,W,8] (+ the depth prior's depth and alpha) against ``packed`` [H,W,7|9] (S, R, L[, the
    edge weights]): the values of the torch terms (module docstring); "depth" is unweighted and not in the sum.
    ``linear``: a raw scene's target with ``prior_snr`` > 0 weighs the priors' L1 by :func:`prior_confidence`."""
    H, W = image.shape[0], image.shape[1]
    conf = None
    if linear is not None and linear.prior_snr > 0:
        conf = prior_confidence(to_bchw(packed[..., :3]), linear)[0, 0].contiguous()
    x9, y9, sums = _SupervisionPass.apply(image, packed, conf, sup)
    noise = sup.rec_form >= REC_FORMS["noise"]
    means, over = _sum_scales(H, W, noise, sums.dtype, sums.device)
    scaled = sums
    if noise:  # the noise forms' reconstruction is a weighted mean: over the weights' sum (a constant of the step)
        scaled = sums / torch.where(over, sums.detach()[SUM_W], 1.0)
    v = means @ scaled  # [4]: sup_r's, sup_l's and sup_rec's L1 means, L_TV (one kernel, not a dozen, issue 65)
    values = v[:3]
    if lambda_ssim:
        s = ssim_map(x9[None], y9[None]).reshape(3, -1).mean(1)  # y9 is a target: the fused SSIM
        values = torch.lerp(values, 1.0 - s, lambda_ssim)  # (1 − λ)·L1 + λ·(1 − SSIM)
    terms = dict(zip(("sup_r", "sup_l", "sup_rec"), values.unbind()))
    total = values @ _weights(weights, sums.dtype, sums.device)
    terms["tv"] = v[3]
    if image.shape[-1] == 8:
        # (disparity / coverage, x-steps / their mask, y-steps / theirs): the sums at 6, 8, 10 over those at 7, 9, 11
        q = sums[SUM_DISP::2] / sums.detach()[SUM_COV::2].clamp_min(1.0)
        terms["depth"] = q[1:].sum() / q[0].detach().clamp_min(DEPTH_EPS)
    return total, terms
