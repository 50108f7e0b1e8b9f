"""Training losses of RetinexGS (paper Sec. II.D, Eqs. 3–10). Pure torch, all differentiable.

Layout: every image argument is a [B,C,H,W] float tensor (use :func:`to_bchw` for a rendered [H,W,C]
map). Every loss returns a scalar tensor averaged over the batch.

Decomposition loss (weights from the paper):
    L_decomp = L_sup + 0.01·L_TV + 0.01·L_SH
    L_sup    = 0.5·Ls(R̂, R) + 0.5·Ls(L̂, L) + 1·Ls(R̂∘L̂, S)                     (Eq. 4)
    Ls(x, y) = (1−λ)·|x−y|₁ + λ·(1 − SSIM(x, y)), λ = 0.2                   (3DGS's 0.8/0.2)
Enhancement loss on S_enh (R̂∘L̂^g in the paper; the tone map of ``model.enhancement.tone``), switched on after
step 3000 (the trainer decides):
    L_enhance = 0.1·L_spa + 1·L_exp + 0.5·L_col                             (Eq. 7)

Choices where the paper and the Zero-DCE reference code differ (each is an option; configs/paper.yaml
picks the paper's, configs/default.yaml the product's, with the reasons in the files):
    - L_spa: Zero-DCE's squared differences of 4×4-pooled neighbour gradients, or the paper's L1 of
      full-resolution gradient differences (Eq. 8); optionally on mean-normalised images.
    - L_exp: squared (Zero-DCE's code) or absolute (Eq. 9) deviation of 16×16-pooled (or whole-image)
      brightness from E, on the enhanced image (the paper; the default over the whole image at E = 0.5) or on
      the enhanced illumination (the previous default).
    - L_col: the paper's Σ(m_p − m_q)² by default; Zero-DCE's sqrt(Σ d^4) on request (it has an
      infinite gradient at a perfectly grey image, so it gets an eps inside the root).
    - L_SH: mean of squares (the default: its weight does not scale with the number of Gaussians) or the
      sum of Eq. 6.
"""
from __future__ import annotations

from typing import Dict, NamedTuple, Optional, Tuple, Union

import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from retinexgs.evaluate.metrics import cached_constant, check_bchw, gaussian_window, ssim
from retinexgs.data.raw_noise import PREVIEW_RADIUS
from retinexgs.model.tone import highlight_capped_mean
from retinexgs.model.tones.fused_curve import to_linear, tone_curve
from retinexgs.model.tones import Tone, get_tone
from retinexgs.render.ssim import fused_ssim_map
from retinexgs.config.schema import Loss

__all__ = [
    "to_bchw", "gaussian_window", "ssim", "ssim_map", "noise_variance", "exposed", "l1_ssim",
    "LinearTarget", "RELATIVE_EPS", "PRIOR_WINDOW", "prior_confidence", "linear_weights", "linear_reconstruction", "reconstruction_loss",
    "supervision_loss", "chroma_weighted", "tv_loss", "edge_weights", "DEPTH_MIN_ALPHA", "DEPTH_EPS",
    "depth_smoothness_loss", "sh_sparsity_loss",
    "spatial_consistency_loss", "exposure_loss", "color_constancy_loss", "enhancement_loss",
]

Terms = Dict[str, torch.Tensor]


def to_bchw(x: torch.Tensor) -> torch.Tensor:
    """[H,W,C] -> [1,C,H,W] (a [B,C,H,W] tensor is returned unchanged)."""
    if x.dim() == 4:
        return x
    if x.dim() == 3:
        return x.permute(2, 0, 1).unsqueeze(0)
    raise ValueError(f"expected [H,W,C] or [B,C,H,W], got shape {tuple(x.shape)}")



# The training SSIM's window and constants: 3DGS's (11 taps, σ = 1.5, data range 1), as metrics.ssim's defaults.
SSIM_WINDOW, SSIM_SIGMA = 11, 1.5
SSIM_C1, SSIM_C2 = 0.01 ** 2, 0.03 ** 2


def ssim_map(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The SSIM map of ``x`` against ``y`` ([B,C,H,W], one shape) with "same" padding: the training losses' SSIM.

    On the fused kernels (:func:`retinexgs.render.ssim.fused_ssim_map`, one pass each way) where ``y`` is a target
    (no gradient); otherwise on :func:`ssim`, its torch twin (the values agree to rounding)."""
    if y.requires_grad:
        return ssim(x, y, window=SSIM_WINDOW, sigma=SSIM_SIGMA, reduction="none")
    taps = cached_constant(("ssim_taps", SSIM_WINDOW, SSIM_SIGMA),
                           lambda: gaussian_window(SSIM_WINDOW, SSIM_SIGMA, dtype=torch.float64))
    check_bchw(x, y)
    return fused_ssim_map(x, y, taps, SSIM_C1, SSIM_C2)

# Immerkær's noise mask: the second difference along x times the second difference along y, so it is zero on
# anything at most linear along one axis (planes, ramps, x², y², xy) and on a smooth image responds mostly to
# noise; Σ mask² = 36.
_NOISE_MASK = ((1.0, -2.0, 1.0), (-2.0, 4.0, -2.0), (1.0, -2.0, 1.0))


def _noise_mask(c: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Immerkær's mask as depthwise weights [c,1,3,3] (kept in ``_WEIGHTS``, like the SSIM window)."""
    return cached_constant(("noise", c, dtype, torch.device(device)),
                     lambda: torch.tensor(_NOISE_MASK, dtype=dtype, device=device).expand(c, 1, 3, 3).contiguous())


def noise_variance(y: torch.Tensor) -> torch.Tensor:
    """Per image and channel, the variance of white noise in ``y`` [B,C,H,W] → [B,C,1,1] (H, W ≥ 3).

    Immerkær (1996) with a median for the mean: the 3×3 mask responds to noise with standard deviation 6σ, and
    the median of its magnitude, unlike the mean, ignores the few pixels on edges and texture (a Gaussian's
    median |r| is 0.6745 of its σ).
    """
    check_bchw(y)
    if min(y.shape[-2:]) < 3:
        raise ValueError(f"noise_variance needs an image of at least 3×3, got {tuple(y.shape[-2:])}")
    b, c, h, w = y.shape
    r = F.conv2d(y, _noise_mask(c, y.dtype, y.device), groups=c).abs().reshape(b, c, -1)
    sigma = r.median(dim=-1).values / (0.6745 * 6.0)
    return (sigma * sigma).reshape(b, c, 1, 1)


def exposed(x: torch.Tensor, gain: torch.Tensor, extended: bool = False) -> torch.Tensor:
    """srgb(gain · lin(x)) for sRGB-encoded ``x``: the photo as a longer exposure shows it (the default's tone at
    g = 1, :mod:`retinexgs.model.tone`), without the clip at white, so an over-bright render keeps its gradient.

    ``gain``: a scalar tensor (1 / lin(L_ref)). Used to compare the reconstruction with the photo where the
    enhanced output is judged: the sRGB curve and the gain stretch the darkest levels far more than the mid-tones.
    ``extended``: ``x`` is a raw view's unclipped encoding (:func:`retinexgs.data.srgb.linear_to_srgb_extended`),
    negative values kept along the curve's linear segment.
    """
    form = "extended" if extended else "open"
    return tone_curve(x, gain, 1.0, form, form)  # one kernel each way (fused_curve)


class LinearTarget(NamedTuple):
    """A raw scene's reconstruction in linear light (``loss.raw.mode``, issue 52 stage 3b): ``mode`` "noise" or
    "relative" (:func:`linear_weights`); ``a``, ``b``: the views' noise var = a·y + b per channel, [1,3,1,1]
    tensors (:mod:`retinexgs.data.raw_noise`); ``gain``: the exposure the error is measured at (a scalar tensor;
    None: the reconstruction's gain, which the noise floor may cap for its SSIM).

    Why its own gain: the term's weights are normalised, so the gain sets its size beside the other terms; the
    noise floor's cap (``loss.rec_noise_floor``) is about SSIM copying exposed noise and would shrink the term
    by the cap² (on a noisy capture 100× or more), leaving the 2D priors to decide the light."""
    mode: str
    a: torch.Tensor
    b: torch.Tensor
    gain: Optional[torch.Tensor] = None
    unit: str = "plain"
    prior_snr: float = 0.0


# RawNeRF's ε (Mildenhall et al., CVPR 2022, Sec. 3.2), in exposed units (the scene's full light at 1).
RELATIVE_EPS = 1e-3


def linear_weights(x: torch.Tensor, target: LinearTarget, gain: torch.Tensor, normalise: bool = True) -> torch.Tensor:
    """Per-pixel weights (no gradient) of :func:`linear_reconstruction`, normalised to mean 1 per image (else the
    inverse variances of the exposed error, gain·(x − y)), from the render's own linear light ``x`` [B,C,H,W]:

    - ``noise``: 1 / (a·x + b), the inverse of the noise variance at the render's value: the weighted least
      squares that is the Gaussian likelihood of the views under their Poisson-Gaussian noise;
    - ``relative``: 1 / (gain·x + ε)², RawNeRF's weights (the variance taken as proportional to the signal²,
      a tone-mapped L2 in effect).

    Taken at the render rather than at the noisy target, so that a pixel's weight does not follow its noise."""
    with torch.no_grad():
        xs = x.clamp_min(0.0)
        if target.mode == "noise":
            w = 1.0 / ((target.a * xs + target.b) * gain ** 2)
        elif target.mode == "relative":
            w = 1.0 / (gain * xs + RELATIVE_EPS) ** 2
        else:
            raise ValueError(f"unknown linear reconstruction mode {target.mode!r} (noise | relative)")
        return w / w.mean(dim=(1, 2, 3), keepdim=True) if normalise else w


PRIOR_WINDOW = 2 * PREVIEW_RADIUS + 1  # the raw preview's window: what the priors could resolve


def prior_confidence(S: torch.Tensor, target: LinearTarget) -> torch.Tensor:
    """[B,1,H,W] in [0, 1], no gradient: how well a raw view's 2D priors can know the light at each pixel
    (``loss.raw.prior_snr`` k > 0). The priors come from a preview averaged over n×n windows (n =
    :data:`PRIOR_WINDOW`, 9) and then clipped; where that window's mean m of the view's light lies within k of its
    own noise σ_m = sqrt((a·m + b) / n²) of
    black, the clip lifts and tints it, so the prior says nothing of the light there. The weight is
    min over channels of clamp(m / (k·σ_m), 0, 1)."""
    with torch.no_grad():
        y = to_linear(S, "extended")
        r = PRIOR_WINDOW // 2
        m = F.avg_pool2d(F.pad(y, (r, r, r, r), mode="replicate"), PRIOR_WINDOW, 1)
        sigma = ((target.a * m.clamp_min(0.0) + target.b) / PRIOR_WINDOW ** 2).clamp_min(1e-20).sqrt()
        return (m / (target.prior_snr * sigma)).clamp(0.0, 1.0).amin(dim=1, keepdim=True)


def linear_reconstruction(rec: torch.Tensor, S: torch.Tensor, target: LinearTarget,
                          gain: Optional[torch.Tensor] = None) -> torch.Tensor:
    """mean(w · (gain·(lin(R̂∘L̂) − lin(S)))²): R̂∘L̂ [B,3,H,W] against a raw view ``S`` (its unclipped encoding,
    :func:`retinexgs.data.srgb.linear_to_srgb_extended`) in linear light, with :func:`linear_weights`.

    Why linear and squared: a raw view's noise is zero-mean around the light in linear values, negative values
    included, so the least-squares fit of many views converges to the light itself; an absolute or squared error
    on encoded (sRGB) or clipped values converges to a median or a mean biased by the curve or the clip (the lifted
    blacks of a JPEG capture). ``gain`` (1 / lin(L_ref), the reconstruction's exposure; None: 1) puts the error in
    the units the enhanced image is judged in, so the term's size is comparable to the other terms' (the target's
    own ``gain`` where it has one)."""
    check_bchw(rec, S)
    x, y = to_linear(rec, "open"), to_linear(S, "extended")
    gain = target.gain if target.gain is not None else gain
    g = rec.new_ones(()) if gain is None else gain
    if target.unit == "plain":
        w = linear_weights(x, target, g)
        return (w * (g * (x - y)) ** 2).mean()
    if target.unit != "sigma":
        raise ValueError(f"unknown linear reconstruction unit {target.unit!r} (plain | sigma)")
    # sigma: Σ w·e² / (2·sqrt(mean w)) per image, w the weights on the exposed error e unnormalised (1 / its
    # variance): a pixel at the image's typical σ = 1 / sqrt(mean w) is pulled with force e / σ, 1 at one σ, as
    # an L1 pulls with 1 everywhere. The normalised form (plain) pulls with 2·e·w/mean(w), about σ at one σ: on a
    # dark capture far weaker than the 2D priors' L1 terms, which then decide the shadows' light.
    w = linear_weights(x, target, g, normalise=False)
    with torch.no_grad():
        scale = 0.5 / w.mean(dim=(1, 2, 3), keepdim=True).sqrt()
    return (w * scale * (g * (x - y)) ** 2).mean()


def l1_ssim(x: torch.Tensor, y: torch.Tensor, lambda_ssim: float = 0.2,
            ssim_xy: Optional[Tuple[torch.Tensor, torch.Tensor]] = None) -> torch.Tensor:
    """Ls(x, y) = (1−λ)·mean|x−y| + λ·(1 − SSIM(x, y)): 3DGS's photometric loss, SSIM with "same" padding.

    ``y`` may have 1 channel where ``x`` has C (or vice versa): it is broadcast. ``ssim_xy``: the pair the SSIM
    part compares, when it is not (x, y).
    """
    check_bchw(x, y)
    if x.shape != y.shape:
        x, y = torch.broadcast_tensors(x, y)
    l1 = (x - y).abs().mean()
    if lambda_ssim == 0:
        return l1
    xs, ys = (x, y) if ssim_xy is None else torch.broadcast_tensors(*ssim_xy)
    return (1.0 - lambda_ssim) * l1 + lambda_ssim * (1.0 - ssim_map(xs, ys).mean())


def _reconstruction_pairs(rec: torch.Tensor, S: torch.Tensor, gain: Optional[torch.Tensor], l1_exposed: bool,
                          extended: bool = False):
    """((x, y) for the L1, (x, y) for the SSIM) of the reconstruction term: R̂∘L̂ and S as they are, or exposed
    (``extended``: S is a raw view's unclipped encoding)."""
    if gain is None:
        return (rec, S), (rec, S)
    rec_e, S_e = torch.broadcast_tensors(exposed(rec, gain), exposed(S, gain, extended))
    return ((rec_e, S_e) if l1_exposed else (rec, S)), (rec_e, S_e)


def reconstruction_loss(rec: torch.Tensor, S: torch.Tensor, lambda_ssim: float = 0.2,
                        gain: Optional[torch.Tensor] = None, l1_exposed: bool = True,
                        linear: Optional[LinearTarget] = None) -> torch.Tensor:
    """Ls(R̂∘L̂, S) alone (no 2D priors), with the options of :func:`supervision_loss`'s reconstruction term."""
    check_bchw(rec, S)
    if linear is not None:
        (x, y), (xs, ys) = _reconstruction_pairs(rec, S, gain, False, True)
        lin = linear_reconstruction(rec, S, linear, gain)
        if lambda_ssim == 0:
            return lin
        return (1.0 - lambda_ssim) * lin + lambda_ssim * (1.0 - ssim_map(xs, ys).mean())
    (x, y), (xs, ys) = _reconstruction_pairs(rec, S, gain, l1_exposed)
    return l1_ssim(x, y, lambda_ssim, None if xs is x else (xs, ys))


def chroma_weighted(x: torch.Tensor, luma: float) -> torch.Tensor:
    """x − (1 − ``luma``)·mean_c x: x [B,C,H,W] with its channel mean (its luma) scaled by ``luma``, its chroma (x
    minus that mean) kept."""
    return x - (1.0 - luma) * x.mean(dim=1, keepdim=True)


def supervision_loss(R_hat: torch.Tensor, L_hat: torch.Tensor, R: torch.Tensor, L: torch.Tensor,
                     S: torch.Tensor, w_r: Union[float, torch.Tensor] = 0.5, w_l: Union[float, torch.Tensor] = 0.5,
                     w_s: float = 1.0,
                     lambda_ssim: float = 0.2, rec_gain: Optional[torch.Tensor] = None,
                     rec_l1_exposed: bool = True, linear: Optional[LinearTarget] = None,
                     r_luma: float = 1.0) -> Tuple[torch.Tensor, Terms]:
    """L_sup of Eq. 4: w_r·Ls(R̂, R) + w_l·Ls(L̂, L) + w_s·Ls(R̂∘L̂, S).

    Args:
        R_hat, L_hat: rendered reflectance and illumination maps [B,3,H,W] (L̂ may be [B,1,H,W]).
        R, L, S: the 2D decomposer's reflectance and illumination and the low-light input; L may have
            1 channel (broadcast against L̂).
        rec_gain: when given, the reconstruction term's SSIM compares ``exposed(R̂∘L̂)`` with ``exposed(S)``
            (:func:`exposed`) instead of the dark values, and so does its L1 if ``rec_l1_exposed``.
        linear: a raw scene's :class:`LinearTarget`: the reconstruction term's L1 is replaced by
            :func:`linear_reconstruction` (S is the view's unclipped encoding) and its SSIM compares exposed
            values with S exposed unclipped.

    Returns:
        (total, {"sup_r", "sup_l", "sup_rec"}) — the unweighted terms, for logging.
    """
    check_bchw(R_hat, L_hat, R, L, S)
    # The three Ls terms as one channel-stacked L1 + SSIM (SSIM is per channel, so stacking changes no value;
    # it is one set of kernels instead of three). Each pair is broadcast to a common channel count first.
    rec = R_hat * L_hat
    if r_luma != 1.0:
        R_hat, R = chroma_weighted(R_hat, r_luma), chroma_weighted(R, r_luma)
    lin_rec = None if linear is None else linear_reconstruction(rec, S, linear, rec_gain)
    (rec, target), (rec_s, target_s) = _reconstruction_pairs(rec, S, rec_gain, rec_l1_exposed and linear is None,
                                                             linear is not None)
    pairs = [torch.broadcast_tensors(a, b) for a, b in ((R_hat, R), (L_hat, L), (rec, target))]
    sizes = [a.shape[1] for a, _ in pairs]
    x = torch.cat([a for a, _ in pairs], dim=1)
    y = torch.cat([b for _, b in pairs], dim=1)
    err = (x - y).split(sizes, dim=1)
    if linear is not None and linear.prior_snr > 0:  # the priors' L1 only where they resolve the light
        conf = prior_confidence(S, linear)
        prior_r, prior_l = (conf * err[0].abs()).mean(), (conf * err[1].abs()).mean()
    else:
        prior_r, prior_l = err[0].abs().mean(), err[1].abs().mean()
    l1 = torch.stack([prior_r, prior_l,
                      err[2].abs().mean() if lin_rec is None else lin_rec])
    if lambda_ssim:
        if rec_s is not rec:
            x, y = torch.cat([x[:, :-sizes[2]], rec_s], dim=1), torch.cat([y[:, :-sizes[2]], target_s], dim=1)
        s = torch.stack([m.mean() for m in ssim_map(x, y).split(sizes, dim=1)])
        values = (1.0 - lambda_ssim) * l1 + lambda_ssim * (1.0 - s)
    else:
        values = l1
    terms = dict(zip(("sup_r", "sup_l", "sup_rec"), values.unbind()))
    total = w_r * terms["sup_r"] + w_l * terms["sup_l"] + w_s * terms["sup_rec"]
    return total, terms


def tv_loss(R_hat: torch.Tensor) -> torch.Tensor:
    """L_TV of Eq. 5: mean|R̂[..., i, j+1] − R̂[..., i, j]| + mean|R̂[..., i+1, j] − R̂[..., i, j]|.

    Anisotropic L1 of forward differences, each direction averaged over its own (B·C·H·(W−1) or
    B·C·(H−1)·W) entries, so the value does not depend on the image size.
    """
    check_bchw(R_hat)
    dx = (R_hat[..., :, 1:] - R_hat[..., :, :-1]).abs()
    dy = (R_hat[..., 1:, :] - R_hat[..., :-1, :]).abs()
    zero = R_hat.new_zeros(())
    return (dx.mean() if dx.numel() else zero) + (dy.mean() if dy.numel() else zero)


def edge_weights(guide: torch.Tensor, edge: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """exp(−edge·|∂I|) of the channel mean I of ``guide`` [B,C,H,W]: ([B,1,H,W−1], [B,1,H−1,W]) weights of
    the horizontal and vertical forward differences; near 1 in flat regions, small across the image's edges."""
    check_bchw(guide)
    g = guide.mean(1, keepdim=True)
    wx = torch.exp(-edge * (g[..., :, 1:] - g[..., :, :-1]).abs())
    wy = torch.exp(-edge * (g[..., 1:, :] - g[..., :-1, :]).abs())
    return wx, wy


DEPTH_MIN_ALPHA, DEPTH_EPS = 0.5, 1e-6  # the depth prior's coverage threshold and its depth floor


def depth_smoothness_loss(depth: torch.Tensor, alpha: torch.Tensor, wx: torch.Tensor, wy: torch.Tensor,
                          min_alpha: float = DEPTH_MIN_ALPHA, eps: float = DEPTH_EPS) -> torch.Tensor:
    """Edge-aware first-order smoothness of the rendered disparity (Monodepth's form, not in the paper).

    ``depth`` [B,1,H,W] is the alpha-weighted depth Σ wᵢzᵢ and ``alpha`` [B,1,H,W] the accumulated Σ wᵢ of the
    same render; ``wx``, ``wy``: :func:`edge_weights` of a guide image. The disparity α/Σwᵢzᵢ (the inverse of
    the expected depth) is divided by its mean over the covered pixels (alpha ≥ ``min_alpha``), so the term
    does not depend on the scene's scale. Each difference counts only where both its pixels are covered, and
    the two directions are averaged over their own counts.

    Why: where the photos show no texture (a plain wall, more so in the dark, where noise hides what texture
    there is) the reconstruction loss is flat in depth, and Gaussians settle at any depth that reproduces the
    training views' colours; a view past them shows that as floaters. Smooth disparity, except across the
    guide's edges, is the prior that decides such regions.
    """
    check_bchw(depth, alpha, wx, wy)
    covered = (alpha >= min_alpha).to(depth.dtype)
    disp = alpha / depth.clamp_min(eps) * covered
    disp = disp / (disp.sum() / covered.sum().clamp_min(1.0)).detach().clamp_min(eps)
    mx = covered[..., :, 1:] * covered[..., :, :-1]
    my = covered[..., 1:, :] * covered[..., :-1, :]
    dx = (disp[..., :, 1:] - disp[..., :, :-1]).abs() * wx * mx
    dy = (disp[..., 1:, :] - disp[..., :-1, :]).abs() * wy * my
    return dx.sum() / mx.sum().clamp_min(1.0) + dy.sum() / my.sum().clamp_min(1.0)


def sh_sparsity_loss(sh_rest: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """L_SH of Eq. 6 on the higher-order SH coefficients c_{>0} (any shape, e.g. [N,15,3]).

    ``reduction="mean"`` (default) averages the squares over all entries: Eq. 6's sum would grow with
    the number of Gaussians (~1e5–1e6) and swamp the other terms at weight 0.01. ``"sum"`` gives Eq. 6.
    """
    if sh_rest.numel() == 0:
        return sh_rest.new_zeros(())
    sq = sh_rest.square()
    if reduction == "mean":
        return sq.mean()
    if reduction == "sum":
        return sq.sum()
    raise ValueError("reduction must be 'mean' or 'sum'")


def _pair_coefficients(h: int, w: int, dtype: torch.dtype, device) -> torch.Tensor:
    """[1,1,h,w]: 8 − (a region's sides on the image border), the diagonal of :class:`_PairEnergy`'s A."""
    def build() -> torch.Tensor:
        border = torch.zeros((1, 1, h, w), dtype=dtype, device=device)
        border[..., 0, :] += 1
        border[..., h - 1, :] += 1
        border[..., :, 0] += 1
        border[..., :, w - 1] += 1
        return 8.0 - border
    return cached_constant(("spa_pair_coefficients", h, w, dtype, torch.device(device or "cpu")), build)


class _PairEnergy(torch.autograd.Function):
    """L_spa's sum over every region's 4 neighbours of (d_k − d_j)², d [B,1,h,w] (zero outside the image), over
    d's size. Taken pair by pair, a pair of two regions counts twice (once from each) and a region with the zero
    outside once, so the sum is the quadratic form dᵀA d with (A d)_k = 2 Σ_inner j (d_k − d_j) + (border sides)·d_k
    = (8 − border sides)·d_k − 2·(sum of the 4 neighbours), and its gradient is 2 A d. One function, its gradient
    from the A d its forward made (17 operators fewer in the loss graph, issue 65)."""

    @staticmethod
    def forward(ctx, d: torch.Tensor) -> torch.Tensor:
        h, w = d.shape[-2:]
        # the 4 neighbours' sum from the zero-padded map (not a convolution: cuDNN's may round through TF32)
        p = F.pad(d, (1, 1, 1, 1))
        neighbours = p[..., :h, 1:w + 1] + p[..., 2:, 1:w + 1] + p[..., 1:h + 1, :w] + p[..., 1:h + 1, 2:]
        Ad = torch.addcmul(neighbours, _pair_coefficients(h, w, d.dtype, d.device), d, value=-0.5).mul_(-2.0)
        ctx.save_for_backward(Ad)
        ctx.scale = 1.0 / d.numel()
        return torch.dot(d.reshape(-1), Ad.reshape(-1)) * ctx.scale

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (Ad,) = ctx.saved_tensors
        return Ad * (grad * (2.0 * ctx.scale))


def _mean_normalized(x: torch.Tensor) -> torch.Tensor:
    """Each image of [B,C,H,W] divided by its mean brightness: terms on it ignore a global gain."""
    return x / x.mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-6)


def _pooled_brightness(x: torch.Tensor, pool: int, scale_invariant: bool) -> torch.Tensor:
    """The channel mean of [B,C,H,W] average-pooled ``pool``×``pool`` (L_spa's region means Y), with
    ``scale_invariant`` divided by the image's mean brightness. The division comes after the pooling, on pool² times
    fewer values: dividing by a per-image number commutes with the channel mean and the pooling, and on the full image
    it and its backward were a tenth of the step's per-pixel traffic (issue 65)."""
    y = x.mean(1, keepdim=True)
    pooled = F.avg_pool2d(y, pool)
    if not scale_invariant:
        return pooled
    # with no partial region at the border the regions' mean is the image's (a small reduction, not a full-size one)
    whole = y.shape[-2] % pool == 0 and y.shape[-1] % pool == 0
    return pooled / (pooled if whole else y).mean(dim=(2, 3), keepdim=True).clamp_min(1e-6)


def spatial_consistency_loss(enh: torch.Tensor, orig: torch.Tensor, pool: int = 4, form: str = "zero_dce",
                             scale_invariant: bool = False) -> torch.Tensor:
    """L_spa (Eq. 8): keeps the local contrast structure of ``orig`` in ``enh``.

    form="zero_dce": both images are averaged over channels and ``pool``×``pool``-average-pooled (region
    means Y); for each region k and each of its 4 neighbours j (zero outside the image), D_kj = Y_k − Y_j.
    Loss = mean over k and batch of Σ_j (D_kj(enh) − D_kj(orig))².
    form="paper": Eq. 8 as written, ‖∇S_enh − ∇S‖₁: mean absolute difference of the full-resolution
    forward differences (x and y, per channel).

    ``scale_invariant`` divides each image by its mean brightness first. Without it the term compares the
    brightened image's gradients with the dark input's, so it rewards a darker output (it trades
    brightness for contrast); with it only the *structure* of the contrast is compared.
    """
    check_bchw(enh, orig)
    if form == "paper":
        if scale_invariant:
            enh, orig = _mean_normalized(enh), _mean_normalized(orig)
        dx = (enh[..., :, 1:] - enh[..., :, :-1]) - (orig[..., :, 1:] - orig[..., :, :-1])
        dy = (enh[..., 1:, :] - enh[..., :-1, :]) - (orig[..., 1:, :] - orig[..., :-1, :])
        return dx.abs().mean() + dy.abs().mean()
    if form != "zero_dce":
        raise ValueError("form must be 'zero_dce' or 'paper'")
    # D_kj(enh) − D_kj(orig) = d_k − d_j with d = Y(enh) − Y(orig): the differences are linear, and the sum over
    # every region's neighbours is a quadratic form in d (_PairEnergy).
    d = _pooled_brightness(enh, pool, scale_invariant) - _pooled_brightness(orig, pool, scale_invariant)
    return _PairEnergy.apply(d)


def exposure_loss(enh: torch.Tensor, E: float = 0.6, patch: int = 16, form: str = "l2",
                  means: Optional[torch.Tensor] = None) -> torch.Tensor:
    """L_exp (Eq. 9): deviation of the brightness Y_k of regions from the target exposure E.

    Y_k = mean brightness (channel mean, then the average over non-overlapping ``patch``² regions; a partial
    border patch is dropped). ``patch=0`` uses one region, the whole image (the right form for one gamma
    per image: a single parameter cannot move every patch to E, and per-patch errors then pull it towards
    flattening the contrast). form="l2": mean (Y_k − E)² (Zero-DCE's code); "l1": mean |Y_k − E| (Eq. 9).
    ``means``: with ``patch=0``, ``enh``'s channel means [B,C] already taken (L_col's too: one pass over the image).
    """
    check_bchw(enh)
    if patch == 0:  # the image's mean brightness: the mean of its channel means
        y = (enh.mean(dim=(2, 3)) if means is None else means).mean(1)
    else:
        y = F.avg_pool2d(enh.mean(1, keepdim=True), patch)
    if form == "l2":
        return (y - E).square().mean()
    if form == "l1":
        return (y - E).abs().mean()
    raise ValueError("form must be 'l2' or 'l1'")


def highlight_meter_applies(tone: Union[str, Tone], c: Loss) -> bool:
    """Whether ``loss.exp_highlight_share`` (config loss section ``c``) acts: it caps the target of the whole-image
    meter (``exp_on: image``, ``exp_patch: 0``; :func:`retinexgs.model.tone.highlight_capped_mean`) of a tone whose
    ``meter_applies`` (``exposure``'s); the other tones and meters (the paper's, the ablations') ignore it.
    ``tone``: a name or a :class:`~retinexgs.model.tones.Tone`."""
    return get_tone(tone).meter_applies and c.exp_on == "image" and c.exp_patch == 0


def exposure_target(c: Loss, tone: Union[str, Tone], RL: torch.Tensor, shoulder: float):
    """L_exp's target E for the image whose R̂∘L̂ is ``RL`` [..., 3]: ``c.exposure_E``, capped by the highlight
    meter where :func:`highlight_meter_applies` (a 0-d tensor then, no gradient). Training and the 2D proxy both
    meter through this."""
    share = float(c.exp_highlight_share)
    if share > 0 and highlight_meter_applies(tone, c):
        return highlight_capped_mean(RL, c.exposure_E, share, shoulder)
    return c.exposure_E


def color_constancy_loss(enh: torch.Tensor, mode: str = "paper", eps: float = 1e-12,
                         scale_invariant: bool = False, means: Optional[torch.Tensor] = None) -> torch.Tensor:
    """L_col (Eq. 10): gray-world penalty on the per-image channel means m_r, m_g, m_b; batch mean.

    ``scale_invariant`` divides the means by their average first (a penalty on the colour balance alone:
    without it a darker image always scores better).

    mode="paper": (m_r−m_g)² + (m_r−m_b)² + (m_g−m_b)² (the 3 unordered pairs of Eq. 10).
    mode="zero_dce": sqrt((m_r−m_g)^4 + (m_r−m_b)^4 + (m_g−m_b)^4 + eps) (Zero-DCE's code; eps keeps
    the gradient finite at a grey image). ``means``: ``enh``'s channel means [B,3] already taken.
    """
    check_bchw(enh)
    if enh.shape[1] != 3:
        raise ValueError("color_constancy_loss needs 3 channels")
    if mode not in ("paper", "zero_dce"):
        raise ValueError("mode must be 'paper' or 'zero_dce'")
    m = enh.mean(dim=(2, 3)) if means is None else means
    if scale_invariant:
        m = m / m.mean(dim=1, keepdim=True).clamp_min(1e-6)
    # every ordered pair at once ([B,3,3], the diagonal 0): each unordered pair twice, so half the sum (a few
    # kernels in the loss graph instead of a dozen, issue 65)
    sq = (m[:, :, None] - m[:, None, :]).square()
    if mode == "paper":
        return sq.sum(dim=(1, 2)).mean() * 0.5
    return torch.sqrt(sq.square().sum(dim=(1, 2)) * 0.5 + eps).mean()


def enhancement_loss(enh: torch.Tensor, orig: torch.Tensor, w_spa: float = 0.1, w_exp: float = 1.0,
                     w_col: float = 0.5, E: float = 0.6, color_mode: str = "paper",
                     illumination: Optional[torch.Tensor] = None, exp_patch: int = 16, exp_form: str = "l2",
                     spa_form: str = "zero_dce", scale_invariant: bool = False) -> Tuple[torch.Tensor, Terms]:
    """L_enhance of Eq. 7 on S_enh = R̂∘L_enh with the low-light input (or R̂∘L̂) as ``orig``.

    ``illumination``: when given (the enhanced illumination L_enh, [B,C,H,W]), L_exp measures the exposure
    of the light instead of the image: how bright a normally lit scene looks then depends on its
    reflectance (a white sofa is brighter than a dark bike), as it does in a photograph. The other options
    are those of :func:`exposure_loss`, :func:`spatial_consistency_loss` and :func:`color_constancy_loss`.

    Returns:
        (w_spa·L_spa + w_exp·L_exp + w_col·L_col, {"spa", "exp", "col"}) — unweighted terms.
    """
    # L_exp on the whole image and L_col both start from the image's channel means: taken once (a full-size pass
    # each way fewer)
    means = enh.mean(dim=(2, 3)) if illumination is None and exp_patch == 0 and enh.shape[1] == 3 else None
    parts = {
        "spa": (w_spa, lambda: spatial_consistency_loss(enh, orig, form=spa_form, scale_invariant=scale_invariant)),
        "exp": (w_exp, lambda: exposure_loss(enh if illumination is None else illumination, E, exp_patch, exp_form,
                                             means)),
        "col": (w_col, lambda: color_constancy_loss(enh, color_mode, scale_invariant=scale_invariant, means=means)),
    }
    terms, total = {}, None
    for name, (weight, term) in parts.items():
        if weight == 0:  # logged, not differentiated: its backward would only add zeros (~15 kernels a step)
            with torch.no_grad():
                terms[name] = term()
            continue
        terms[name] = term()
        total = weight * terms[name] if total is None else total + weight * terms[name]
    return (enh.new_zeros(()) if total is None else total), terms
