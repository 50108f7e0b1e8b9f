"""A noise-level-aware denoising prior for noisy views (issue 64, item 1).

A view's light (linear RGB: a raw view's unclipped values, or a photo's sRGB undone) has Poisson–Gaussian noise,
``var(y_c) = a_c·y_c + b_c`` per channel c (:class:`retinexgs.data.raw_noise.RawNoise` for raw views, the capture's
:class:`retinexgs.train.noise.CaptureNoise` for photos). The generalised Anscombe transform makes that noise
unit-variance Gaussian, the denoiser works at σ = 1, and the transform is inverted without bias:

- ``nlm``: OpenCV's non-local means on an orthonormal luma/chroma split of the stabilised channels (unit noise
  in each), the chroma much stronger than the luma (at low light chroma carries far less detail than luma);
- ``chroma``: the luma as ``nlm``'s, the chroma by a guided filter (He et al.) at a large radius, guided by the
  denoised luma: colour follows luma's edges and is otherwise smoothed hard.

The result feeds the 2D priors (``decomposer.denoise``); the views' luminance target stays the unbiased photo.
:func:`denoised_view` caches it per photo by content, as :mod:`retinexgs.retinex.cache` keys LR3M's entries.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import torch.nn.functional as F

from retinexgs.errors import UserError

__all__ = ["METHODS", "BACKENDS", "resolve_backend", "nlm_torch", "DenoiseParams",
           "DenoiseSpec", "NoiseModel", "noise_model", "gat_forward",
           "gat_inverse", "pilot_wiener", "measured_sigma", "denoise_linear", "denoise_view_image", "denoise_key",
           "denoised_view",
           "DENOISE_VERSION", "DENOISED_DIRNAME"]

METHODS = ("none", "nlm", "chroma")
# Who runs the non-local means: OpenCV's (CPU only), torch's :func:`nlm_torch` (CPU or CUDA), or ``auto``: torch
# where the denoiser runs on a CUDA device (12 MP ``chroma``: 0.46 s on an H200 against OpenCV's 3.75 s on 16 cores),
# OpenCV on the CPU (torch's is several times slower there). ``retinexgs bench denoise`` times both.
BACKENDS = ("auto", "torch", "opencv")
DENOISE_VERSION = 1  # part of every cache key: a change of the algorithm recomputes its entries
# Where denoised views are cached in a scene's cache root: <root>/denoised/<method>-<12 hex>/<stem>-<16 hex>.npz
DENOISED_DIRNAME = "denoised"

# Orthonormal luma/chroma basis of the stabilised RGB: rows (R+G+B)/√3, (R−B)/√2, (R−2G+B)/√6. Orthonormal, so each
# output keeps unit noise variance when the channels' noise is independent and of unit variance (after the GAT).
YCC = torch.tensor([[1 / math.sqrt(3), 1 / math.sqrt(3), 1 / math.sqrt(3)],
                     [1 / math.sqrt(2), 0.0, -1 / math.sqrt(2)],
                     [1 / math.sqrt(6), -2 / math.sqrt(6), 1 / math.sqrt(6)]], dtype=torch.float64)


@dataclass(frozen=True)
class DenoiseParams:
    """The denoiser's settings (``decomposer.denoise`` uses these defaults; every one is part of the cache key).

    ``h_luma``/``h_chroma``: non-local means' filter strength in units of the (unit) noise σ after the GAT; chroma
    far stronger because at SNR ≈ 1 its detail is below the noise anyway (``h_chroma`` is read by the ``nlm`` method
    only: ``chroma``, what ``auto`` picks, filters the chroma with the luma-guided filter of ``radius`` and ``eps``). ``patch``/``search``: NLM's template and
    search windows (OpenCV's defaults 7 and 21). ``radius``: the guided chroma filter's window half-size in pixels
    at 640 px wide (scaled with the view's width, so a larger photo gets the same angular support); ``eps``: its
    regulariser in units of σ² (larger: flatter colour, fewer luma edges kept). ``calibrate``: each luma/chroma
    component's noise σ after the GAT is also measured on the view (:func:`_measured_sigma`) and the larger of it
    and the model's 1 is used: a pixel-scale model under-reads the noise at the scale of the filters' patches where
    the pixels' noise is correlated (a demosaiced raw view; a JPEG's quantisation, which removes the finest part of
    the noise; the colour matrix, which mixes the channels' noise)."""
    h_luma: float = 0.8
    h_chroma: float = 4.0
    patch: int = 7
    search: int = 21
    radius: int = 24
    eps: float = 16.0
    calibrate: bool = True

    @classmethod
    def from_mapping(cls, params: Optional[Mapping[str, Any]]) -> "DenoiseParams":
        """Settings from a dict of overrides; UserError (one line) for an unknown name or a bad value."""
        params = dict(params or {})
        known = {f for f in cls.__dataclass_fields__}
        bad = sorted(set(params) - known)
        if bad:
            raise UserError(f"unknown denoiser parameter {bad[0]!r} (known: {', '.join(sorted(known))})")
        if any(isinstance(getattr(cls, k), bool) and not isinstance(v, bool) for k, v in params.items()):
            raise UserError("denoiser parameter 'calibrate' must be true or false")
        try:
            out = cls(**{k: type(getattr(cls, k))(v) for k, v in params.items()})
        except (TypeError, ValueError) as exc:
            raise UserError(f"bad denoiser parameter: {exc}") from None
        if out.h_luma < 0 or out.h_chroma < 0 or out.eps <= 0 or min(out.radius, out.patch, out.search) < 1:
            raise UserError(f"denoiser parameters out of range: {asdict(out)} (h >= 0, eps > 0, radius, patch, "
                            "search >= 1)")
        return out

    def for_views(self, views_per_point: Optional[float], full_up_to: float) -> "DenoiseParams":
        """These settings for a scene whose points lie in ``views_per_point`` training views (the median;
        :meth:`retinexgs.data.Scene.views_per_point`): the multi-view fit averages a point's luma noise over those
        views (its σ falls as 1/√n), so the prior's luma NLM need remove only what the averaging leaves: ``h_luma``
        holds up to ``full_up_to`` views and falls as √(full_up_to / n) above (``decomposer.denoise_luma_views``;
        0 or an unknown count: unchanged). The chroma keeps its strength (only the luma's was measured against the
        view count; experiments/notes/2026-11-29-luma-views.md)."""
        if not full_up_to or views_per_point is None or views_per_point <= full_up_to:
            return self
        return replace(self, h_luma=self.h_luma * math.sqrt(full_up_to / views_per_point))


@dataclass(frozen=True)
class NoiseModel:
    """Per-channel Poisson–Gaussian noise of a view's linear light: ``var(y_c) = a[c]·y_c + b[c]``."""
    a: Tuple[float, float, float]
    b: Tuple[float, float, float]


def noise_model(noise: Any, balance: Optional[Sequence[float]] = None, downscale: float = 1.0) -> NoiseModel:
    """A :class:`NoiseModel` from anything with per-channel ``a`` and ``b`` (a RawNoise, a CaptureNoise, a pair of
    sequences), checked: UserError (one line) when it cannot be used. ``balance``: the white balance applied to the
    view's light (gain g: variance g·a·y + g²·b); ``downscale``: a view d× smaller averages d×d pixels (÷ d²).

    A model with a ≤ 0 in every channel has no shot noise: that is what an unmeasurable capture falls back to
    (RawNoise's "none"), not a real sensor, and the transform would have nothing to stabilise."""
    if isinstance(noise, (tuple, list)) and len(noise) == 2:
        a, b = noise
    else:
        a, b = getattr(noise, "a", None), getattr(noise, "b", None)
    try:
        a = np.asarray(a, np.float64).reshape(-1)
        b = np.asarray(b, np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise UserError("the denoiser needs a noise model with per-channel a and b (var = a·y + b)") from None
    if a.size == 1:
        a = np.repeat(a, 3)
    if b.size == 1:
        b = np.repeat(b, 3)
    if a.size != 3 or b.size != 3:
        raise UserError(f"the denoiser's noise model needs 3 channels of a and b, got {a.size} and {b.size}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise UserError("the denoiser's noise model is not finite (the capture's noise could not be measured): "
                        "set decomposer.denoise=none")
    if np.all(a <= 0):
        raise UserError("the denoiser's noise model has no shot noise (a <= 0 in every channel): the capture's noise "
                        "was not measured; set decomposer.denoise=none")
    if np.any(b < 0):
        raise UserError(f"the denoiser's noise model has a negative read-noise variance b = {b.tolist()}")
    d2 = float(downscale) ** 2
    a, b = a / d2, b / d2
    if balance is not None:
        g = np.asarray(balance, np.float64).reshape(3)
        a, b = a * g, b * g * g
    # A channel without shot noise (a <= 0) takes the others' smallest a: keeps the transform's square root defined.
    a = np.where(a > 0, a, float(a[a > 0].min()))
    return NoiseModel(tuple(float(v) for v in a), tuple(float(v) for v in b))


def _per_channel(v: Sequence[float], x: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(np.asarray(v, np.float64), dtype=x.dtype, device=x.device).reshape(1, 1, -1)


def gat_forward(y: torch.Tensor, a: Sequence[float], b: Sequence[float]) -> torch.Tensor:
    """The generalised Anscombe transform of ``y`` [H,W,C] with ``var(y) = a·y + b`` per channel (a > 0): per
    channel f(y) = 2·sqrt(max(y/a + 3/8 + b/a², 0)), whose noise has variance ≈ 1 (Makitalo & Foi, "Optimal
    inversion of the generalized Anscombe transformation for Poisson-Gaussian noise", IEEE TIP 22(1), 2013: the
    GAT for z = α·p + N(0, σ²) with α = a, σ² = b, written on z/α with σ/α)."""
    a_, b_ = _per_channel(a, y), _per_channel(b, y)
    return 2.0 * torch.sqrt((y / a_ + 0.375 + b_ / (a_ * a_)).clamp_min(0.0))


def gat_inverse(d: torch.Tensor, a: Sequence[float], b: Sequence[float]) -> torch.Tensor:
    """The closed-form approximation of the exact unbiased inverse of :func:`gat_forward` (Makitalo & Foi 2013,
    the same paper): on the normalised scale s = σ/α,
    I(D) = D²/4 + √(3/2)/(4D) − 11/(8D²) + 5√(3/2)/(8D³) − 1/8 − s², clipped at 0, times α. It inverts the
    *expectation* of f(y) (what a denoiser estimates), where the algebraic inverse D²/4 − 3/8 − s² would leave a
    bias of about 1/8·α that matters most in the dark. Below D = 1 the series diverges; the exact inverse is ~0
    there, so D is floored at 1 and the result at 0."""
    a_, b_ = _per_channel(a, d), _per_channel(b, d)
    s2 = b_ / (a_ * a_)
    D = d.clamp_min(1.0)
    r = math.sqrt(1.5)
    inv = 0.25 * D * D + 0.25 * r / D - 1.375 / (D * D) + 0.625 * r / (D * D * D) - 0.125 - s2
    return inv.clamp_min(0.0) * a_


def _box(x: torch.Tensor, r: int) -> torch.Tensor:
    """Mean over a (2r+1)² window of [C,H,W] (reflected at the borders), by running sums: the cost does not grow
    with the radius (a pooling kernel's does, with its area)."""
    k = 2 * r + 1
    p = F.pad(x[None], (r, r, r, r), mode="reflect")[0]
    c = F.pad(p.cumsum(-1), (1, 0))
    p = c[..., k:] - c[..., :-k]
    c = F.pad(p.cumsum(-2), (0, 0, 1, 0))
    return (c[..., k:, :] - c[..., :-k, :]) / (k * k)


def _guided(guide: torch.Tensor, src: torch.Tensor, r: int, eps: float) -> torch.Tensor:
    """He et al.'s guided filter: ``src`` [C,H,W] filtered by the single-channel ``guide`` [1,H,W]."""
    mi, ms = _box(guide, r), _box(src, r)
    cov = _box(guide * src, r) - mi * ms
    var = _box(guide * guide, r) - mi * mi
    k = cov / (var + eps)
    return _box(k, r) * guide + _box(ms - k * mi, r)


# The scale (pixels a side of the averages) at which :func:`_measured_sigma` reads the noise: patches of NLM (7×7)
# and the guided filter's windows average about this many pixels a side. fox-dark at 1000 e⁻, one view, the luma's σ
# after the GAT on 1×1, 2×2, 4×4 averages: raw 0.08, 0.48, 1.03 (its demosaic and the colour matrix correlate
# the noise); the camera JPEG of the same photons 1.02, 4.1, 8.2 (its pixel-scale model under-reads it ~8×).
_SIGMA_SCALE = 4


def _measured_sigma(x: torch.Tensor, scale: int = _SIGMA_SCALE) -> float:
    """The noise σ of one component ``x`` [H,W] as seen at ``scale`` × ``scale`` averages: Immerkær's estimate
    (J. Immerkær, "Fast noise variance estimation", CVIU 64(2), 1996) on the averages, times ``scale`` (the factor by
    which such an average divides white noise's σ). Texture reads as noise too, so it is an upper bound."""
    if min(x.shape) < 3 * scale:
        scale = 1
    y = F.avg_pool2d(x[None, None], scale)[0, 0] if scale > 1 else x
    k = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], dtype=y.dtype, device=y.device)
    c = F.conv2d(y[None, None], k[None, None])[0, 0]
    return float(math.sqrt(math.pi / 2.0) * c.abs().mean() / 6.0) * scale


def measured_sigma(x: torch.Tensor, scale: int = _SIGMA_SCALE) -> float:
    """The noise σ of one channel ``x`` [H,W] as seen at ``scale`` × ``scale`` averages (an upper bound: texture reads
    as noise too); public for callers that decide whether to denoise at all (``sfm --denoise auto``)."""
    return _measured_sigma(x, scale)


# OpenCV's fastNlMeansDenoising drops a candidate whose weight is below this share of the centre's (its
# WEIGHT_THRESHOLD): far patches add nothing but rounding. The torch version does the same, to match its output.
_NLM_WEIGHT_FLOOR = 1e-3
# The torch NLM's working set per block of rows (float32 maps of one row of search offsets): bounds its memory at any
# photo size (all 441 offsets of a 21×21 window over a 12 MP photo at once would be ~21 GB a map).
_NLM_BLOCK_BYTES = 1 << 30


def _patch_mean(d: torch.Tensor, n: int, pooled: bool) -> torch.Tensor:
    """The mean over n×n windows (no padding) of ``d`` [K,H,W] -> [K,H−n+1,W−n+1], separably: by pooling
    (``pooled``: CUDA's kernels read the window from cache) or by n shifted adds a side (the CPU's pooling is ~5×
    slower than that)."""
    if pooled:
        return F.avg_pool2d(F.avg_pool2d(d[:, None], (n, 1), stride=1), (1, n), stride=1)[:, 0]
    h, w = d.shape[-2] - n + 1, d.shape[-1] - n + 1
    rows = d[..., 0:w].clone()
    for i in range(1, n):
        rows += d[..., i:i + w]
    out = rows[..., 0:h, :].clone()
    for i in range(1, n):
        out += rows[..., i:i + h, :]
    return out.div_(n * n)


def nlm_torch(x: torch.Tensor, h: float, patch: int = 7, search: int = 21,
              block_bytes: int = _NLM_BLOCK_BYTES) -> torch.Tensor:
    """Non-local means of one channel ``x`` [H,W] (float32, on ``x``'s device), OpenCV's ``fastNlMeansDenoising``
    formula without its 8-bit quantisation: the image reflected at its borders (OpenCV's BORDER_REFLECT_101), each
    pixel the weighted mean of the pixels in its ``search``² window, weight exp(−d/h²) where d is the mean squared
    difference of the two ``patch``² patches (0 where below :data:`_NLM_WEIGHT_FLOOR`). Computed per row of search
    offsets: shift (a strided view, no copy), squared difference, a separable box mean, exp, accumulate; in blocks
    of rows of at most about ``block_bytes``. ``h`` <= 0 returns ``x``."""
    if x.dim() != 2:
        raise UserError(f"non-local means needs one [H,W] channel, got {list(x.shape)}")
    if h <= 0:
        return x
    t, s = (patch | 1) // 2, (search | 1) // 2
    height, width = x.shape
    if min(height, width) <= s + t:  # reflection needs the image larger than the pad
        raise UserError(f"the image ({height}x{width}) is too small for non-local means' {2 * s + 1}-pixel search "
                        f"and {2 * t + 1}-pixel patch windows")
    pad = F.pad(x.float()[None, None], (s + t,) * 4, mode="reflect")[0, 0]
    n, wide = 2 * s + 1, width + 2 * t
    inv_h2 = 1.0 / (float(h) * float(h))
    pooled = x.is_cuda
    # Rows per block: about 4 float32 maps of one row of offsets ([n, rows, W+2t]) live at once.
    rows = int(max(1, min(height, block_bytes // (4 * 4 * n * wide) - 2 * t)))
    out = torch.empty(height, width, dtype=torch.float32, device=x.device)
    for y0 in range(0, height, rows):
        y1 = min(height, y0 + rows)
        hh = y1 - y0
        centre = pad[s + y0:s + y1 + 2 * t, s:s + wide]           # this block's patches: the image padded by t
        num = torch.zeros(hh, width, dtype=torch.float32, device=x.device)
        den = torch.zeros_like(num)
        for dy in range(-s, s + 1):
            band = pad[s + y0 + dy:s + y1 + 2 * t + dy, :]        # [hh+2t, W+2t+2s]
            shifted = band.unfold(1, wide, 1).permute(1, 0, 2)     # [n, hh+2t, W+2t]: the n dx shifts, a view
            d = _patch_mean((shifted - centre).square_(), 2 * t + 1, pooled)
            w = torch.exp_(d.mul_(-inv_h2))                        # [n, hh, W]
            w.masked_fill_(w < _NLM_WEIGHT_FLOOR, 0.0)
            den += w.sum(0)
            num += w.mul_(shifted[:, t:t + hh, t:t + width]).sum(0)
        out[y0:y1] = num.div_(den)  # the centre's own weight is 1: never 0
    return out


def _nlm(x: np.ndarray, h: float, p: DenoiseParams) -> np.ndarray:
    """OpenCV non-local means of one channel ``x`` [H,W] with unit noise σ: mapped to 8 bits with the noise at
    ``scale`` levels (a finer step than that only costs range), denoised with h = ``h``·σ, mapped back."""
    import cv2

    if h <= 0:
        return x
    lo, hi = np.percentile(x, [0.1, 99.9])
    # 8-bit levels per σ: as many as the range allows (at least 1), at most 8 (quantisation then adds <0.2 % noise).
    scale = float(np.clip(250.0 / max(hi - lo, 1e-6), 1.0, 8.0))
    off = lo - 2.0 / scale
    u8 = np.clip((x - off) * scale, 0, 255).round().astype(np.uint8)
    out = cv2.fastNlMeansDenoising(u8, None, h=float(h * scale), templateWindowSize=p.patch | 1,
                                   searchWindowSize=p.search | 1)
    res = out.astype(np.float32) / scale + off
    # Pixels clipped by the 8-bit window (beyond the percentiles) keep their own value rather than the clip.
    clipped = (x < off) | (x > off + 255.0 / scale)
    return np.where(clipped, x, res).astype(np.float32)


def resolve_backend(backend: str, device: Union[str, torch.device, None]) -> str:
    """``torch`` or ``opencv``: who runs the NLM for ``backend`` (:data:`BACKENDS`) on ``device`` (``auto``: torch on
    CUDA, OpenCV elsewhere). UserError (one line) for an unknown backend."""
    if backend not in BACKENDS:
        raise UserError(f"unknown denoiser backend {backend!r} (decomposer.denoise_backend: {' | '.join(BACKENDS)})")
    if backend != "auto":
        return backend
    return "torch" if device is not None and torch.device(device).type == "cuda" else "opencv"


def denoise_linear(lin: torch.Tensor, noise: NoiseModel, method: str, params: Optional[DenoiseParams] = None,
                   backend: str = "auto", device: Union[str, torch.device, None] = None) -> torch.Tensor:
    """The denoised linear light of ``lin`` [H,W,3] (float, unclipped allowed) under ``noise``: GAT, ``method``
    at unit σ, the unbiased inverse. ``none`` returns ``lin`` unchanged. Runs on ``device`` (default ``lin``'s) and
    returns there; the NLM by ``backend`` (:func:`resolve_backend`: OpenCV's runs on the CPU, no CUDA build of
    OpenCV in the wheels; torch's on ``device``)."""
    if method not in METHODS:
        raise UserError(f"unknown denoiser {method!r} (decomposer.denoise: {' | '.join(METHODS)})")
    dev = torch.device(device) if device is not None else lin.device
    impl = resolve_backend(backend, dev)
    if method == "none":
        return lin
    if lin.dim() != 3 or lin.shape[-1] != 3:
        raise UserError(f"the denoiser needs an [H,W,3] image, got {list(lin.shape)}")
    p = params or DenoiseParams()
    x = lin.to(dev).double()
    d = gat_forward(x, noise.a, noise.b)                       # unit noise per channel
    ycc = torch.einsum("ij,hwj->ihw", YCC.to(d.device), d)    # [3,H,W]: luma, two chroma, unit noise each
    out_ycc = _filter(ycc, method, p, 1.0, impl)
    out = torch.einsum("ij,ihw->hwj", YCC.to(d.device), out_ycc)  # orthonormal: its inverse is its transpose
    return gat_inverse(out, noise.a, noise.b).to(lin.dtype)


def _nlm_any(x: torch.Tensor, h: float, p: DenoiseParams, impl: str) -> torch.Tensor:
    """NLM of one channel ``x`` [H,W] with unit noise σ at strength ``h``·σ, by ``impl`` (torch or opencv), returned
    on ``x``'s device and dtype. An image too small for torch's reflected borders (a side of at most
    search/2 + patch/2 pixels) goes to OpenCV's, which handles it: a thumbnail costs nothing on the CPU."""
    if impl == "torch" and min(x.shape) > (p.search | 1) // 2 + (p.patch | 1) // 2:
        return nlm_torch(x.float(), h, p.patch, p.search).to(x)
    return torch.from_numpy(_nlm(x.cpu().numpy().astype(np.float32), h, p)).to(x)


def _filter(ycc: torch.Tensor, method: str, p: DenoiseParams, floor: float, impl: str = "opencv") -> torch.Tensor:
    """``method`` on the stabilised luma/chroma ``ycc`` [3,H,W] whose model noise σ is ``floor``: NLM (``impl``) on
    the luma, then NLM or the luma-guided filter on the chroma."""
    sig = [max(floor, _measured_sigma(c)) if p.calibrate else floor for c in ycc]
    luma = _nlm_any(ycc[0], p.h_luma * sig[0], p, impl)
    if method == "nlm":
        chroma = torch.stack([_nlm_any(c, p.h_chroma * s, p, impl) for c, s in zip(ycc[1:], sig[1:])])
    else:
        h, w = ycc.shape[-2:]
        r = int(max(1, min(round(p.radius * w / 640.0), (min(h, w) - 1) // 2)))
        chroma = torch.cat([_guided(luma[None], c[None], r, p.eps * s * s) for c, s in zip(ycc[1:], sig[1:])])
    return torch.cat([luma[None], chroma])


def _dct_matrix(n: int, like: torch.Tensor) -> torch.Tensor:
    """The orthonormal DCT-II matrix [n, n] (rows: frequencies): unit white noise stays unit white noise."""
    k = torch.arange(n, dtype=torch.float64)[:, None]
    i = torch.arange(n, dtype=torch.float64)[None, :]
    d = torch.cos(math.pi * (2 * i + 1) * k / (2 * n)) * math.sqrt(2.0 / n)
    d[0] /= math.sqrt(2.0)
    return d.to(like)


def pilot_wiener(lin: torch.Tensor, pilot: torch.Tensor, noise: NoiseModel, block: int = 8,
                 chroma: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The noisy light ``lin`` [H,W,3] (unclipped allowed) filtered with Wiener gains taken from ``pilot`` [H,W,3], a
    cleaner estimate of the same light (issue 64 item 1: the 3D model's render of the view; BM3D's second stage
    takes its gains from a pilot the same way). Both go through the generalised Anscombe transform of ``noise``
    (unit noise) and the orthonormal luma/chroma split; per block×block DCT block (blocks every block/2 pixels,
    overlaps averaged) each coefficient Z of the view is kept as Z·P²/(P² + 1), P the pilot's: what the pilot says
    is signal survives, what it says is noise goes; then the unbiased inverse. Float64 inside; the result in
    ``lin``'s dtype and device. ``chroma``: another estimate of the same light [H,W,3] whose chroma is kept instead
    of the filtered one (a single-view denoiser's: a render's colour blotches pass the chroma gains)."""
    if lin.dim() != 3 or lin.shape[-1] != 3 or pilot.shape != lin.shape:
        raise UserError(f"pilot_wiener needs two [H,W,3] images of one shape, got {list(lin.shape)} and "
                        f"{list(pilot.shape)}")
    if block < 2 or block % 2:
        raise UserError(f"pilot_wiener's block must be an even number >= 2, got {block}")
    a, b = noise.a, noise.b
    ycc = YCC.to(lin.device)

    def stabilised(x: torch.Tensor) -> torch.Tensor:  # [3,H,W] unit-noise luma/chroma
        return torch.einsum("ij,hwj->ihw", ycc, gat_forward(x.double(), a, b))

    z, p = stabilised(lin), stabilised(pilot.to(lin.device))
    h, w = z.shape[-2:]
    step = block // 2
    ph, pw = ((step - (n - block) % step) % step if n >= block else block - n for n in (h, w))
    if ph or pw:  # whole blocks: mirror the last rows and columns (replicate where the image is too small)
        mode = "reflect" if ph < h and pw < w else "replicate"
        z, p = (F.pad(t[None], (0, pw, 0, ph), mode=mode)[0] for t in (z, p))
    size = z.shape[-2:]
    dct = _dct_matrix(block, z)
    basis = torch.kron(dct, dct)  # the 2-D DCT of a row-major flattened block
    Z = basis @ F.unfold(z[:, None], block, stride=step)  # [3, block², blocks]
    P = basis @ F.unfold(p[:, None], block, stride=step)
    kept = basis.t() @ (Z * (P * P / (P * P + 1.0)))
    out = F.fold(kept, size, block, stride=step) / F.fold(torch.ones_like(kept), size, block, stride=step)
    out = out[:, 0, :h, :w]
    if chroma is not None:
        if chroma.shape != lin.shape:
            raise UserError(f"pilot_wiener's chroma must have the view's shape {list(lin.shape)}, got "
                            f"{list(chroma.shape)}")
        out = torch.cat([out[:1], stabilised(chroma.to(lin.device))[1:]])
    out = torch.einsum("ji,jhw->hwi", ycc, out)
    return gat_inverse(out, a, b).to(lin.dtype)


def denoise_view_image(image: torch.Tensor, noise: NoiseModel, method: str, unclipped: bool,
                       params: Optional[DenoiseParams] = None, backend: str = "auto",
                       device: Union[str, torch.device, None] = None) -> torch.Tensor:
    """The 2D priors' photo, float32 [H,W,3] sRGB in [0,1] on ``image``'s device, from a view ``image`` as training
    reads it: a raw view's unclipped encoding (``unclipped``: :func:`retinexgs.data.srgb.linear_to_srgb_extended`)
    or a photo's sRGB. Denoised in linear light on ``device`` (:func:`denoise_linear`, ``backend``), then clipped
    and encoded."""
    from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear, srgb_to_linear_extended

    lin = srgb_to_linear_extended(image.float()) if unclipped else srgb_to_linear(image.float())
    out = denoise_linear(lin, noise, method, params, backend, device)
    return linear_to_srgb(out.clamp(0.0, 1.0)).float().to(image.device).contiguous()


@dataclass(frozen=True)
class DenoiseSpec:
    """What :mod:`retinexgs.retinex.cache` needs to read a view through the denoiser (``decomposer.denoise``): the
    method, the views' noise model (in the light of the images it reads: downscale and white balance applied), the
    settings, and where it runs: ``device`` (None: the CPU) and ``backend`` (``decomposer.denoise_backend``)."""
    method: str
    noise: NoiseModel
    params: DenoiseParams = field(default_factory=DenoiseParams)
    device: Optional[str] = None
    backend: str = "auto"

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise UserError(f"unknown denoiser {self.method!r} (decomposer.denoise: {' | '.join(METHODS)})")
        resolve_backend(self.backend, self.device)  # an unknown backend: one line now, not at the first view

    @property
    def implementation(self) -> str:
        """Who runs the NLM: ``torch`` or ``opencv`` (:func:`resolve_backend`)."""
        return resolve_backend(self.backend, self.device)

    @property
    def recipe(self) -> str:
        """12 hex digits naming the recipe (:func:`denoise_key`)."""
        return denoise_key(self.method, self.noise, self.params, self.implementation)


def denoise_key(method: str, noise: NoiseModel, params: Optional[DenoiseParams] = None,
                implementation: str = "opencv") -> str:
    """12 hex digits naming a denoising recipe (method, its settings, the noise model, the algorithm's version, and
    the NLM's implementation: torch's output differs from OpenCV's 8-bit one by a few levels)."""
    p = params or DenoiseParams()
    fields = {"method": method, "params": asdict(p), "a": [f"{v:.6g}" for v in noise.a],
              "b": [f"{v:.6g}" for v in noise.b], "version": DENOISE_VERSION}
    if implementation != "opencv":  # OpenCV's recipes keep the keys they had before torch's NLM: their caches stay
        fields["implementation"] = implementation
    text = json.dumps(fields, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def denoised_view(path: Union[str, Path], image: torch.Tensor, noise: NoiseModel, method: str, unclipped: bool,
                  cache_root: Optional[Union[str, Path]], params: Optional[DenoiseParams] = None,
                  content: Optional[str] = None, hint: str = "", backend: str = "auto",
                  device: Union[str, torch.device, None] = None) -> Tuple[torch.Tensor, bool]:
    """(:func:`denoise_view_image` of ``image``, whether it came from the cache). Cached under
    ``<cache_root>/denoised/<method>-<recipe>/<stem>-<content>.npz`` (float16) where ``content`` is the photo's
    key (:func:`retinexgs.retinex.cache.prior_key`: its bytes' SHA-256, and its white balance); an entry is trusted
    only if its meta names the same content and recipe. ``cache_root`` None: no cache. Written atomically.
    ``backend``, ``device``: who runs the NLM and where (:func:`denoise_linear`); the recipe names the former."""
    from retinexgs.fileio import atomic_write

    if cache_root is None or content is None:
        return denoise_view_image(image, noise, method, unclipped, params, backend, device), False
    dev = torch.device(device) if device is not None else image.device
    recipe = denoise_key(method, noise, params, resolve_backend(backend, dev))
    folder = Path(cache_root) / DENOISED_DIRNAME / f"{method}-{recipe}"
    target = folder / f"{Path(path).stem}-{content}.npz"
    meta = {"content": content, "recipe": recipe, "method": method, "shape": list(image.shape)}
    hits = sorted(folder.glob(f"*-{content}.npz")) if folder.is_dir() else []
    for hit in hits:  # any stem: a renamed photo reuses its entry
        try:
            with np.load(hit, allow_pickle=False) as z:
                if json.loads(str(z["meta"])) == meta:
                    return torch.from_numpy(z["image"].astype(np.float32)), True
        except Exception:  # truncated or foreign: recomputed below
            pass
    out = denoise_view_image(image, noise, method, unclipped, params, backend, dev)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        arr = out.cpu().numpy().astype(np.float16)
        atomic_write(target, lambda f: np.savez(f, image=arr, meta=np.array(json.dumps(meta, sort_keys=True))),
                     elsewhere=hint or "--set data.cache_dir=DIR")
    except OSError as exc:
        where = f"; put the caches elsewhere with {hint}" if hint else ""
        raise UserError(f"cannot write the denoising cache {folder}: {exc.strerror or exc}{where}") from None
    return out.half().float(), False
