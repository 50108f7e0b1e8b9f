"""Image-quality metrics for evaluating rendered test views against the normal-light references.

All functions take two images of the same shape, [H,W,3] (or [H,W]) float tensors or arrays in [0,1]
(data range 1), compared as given: no colour alignment, no cropping, as peers report on LOM.
Metrics are computed in float64 on the CPU side of the caller's device.

- :func:`psnr`: 10·log10(1 / MSE) in dB (inf for identical images).
- :func:`ssim_metric`: the standard evaluation SSIM (Wang et al. 2004): 11×11 Gaussian window,
  σ = 1.5, C1 = 0.01², C2 = 0.03², "valid" filtering (no padding), population covariances, computed per
  RGB channel and averaged over channels and positions. This is what skimage's
  ``structural_similarity(..., gaussian_weights=True, use_sample_covariance=False, data_range=1,
  channel_axis=-1)`` and the NeRF-family evaluation code compute.
- :func:`gt_mean_align`: the output scaled so that its grey mean equals the truth's (low-light enhancement's
  "GT-mean" evaluation): PSNR / SSIM after it measure everything but the overall brightness, which for a method
  that never sees a normal-light photo is the photographer's choice (docs/benchmarks.md, "Exposure-aligned").
  Reported beside the plain figures, never instead of them.
- :func:`chroma_noise`: the render's CIELAB a*/b* energy at scales of 2-32 px over the truth's (issue 64's colour
  speckle and blotches; 1.0 = the truth's), after the GT-mean alignment; on the caller's device, in float64.
- :func:`lpips_metric` / :func:`lpips_metrics`: LPIPS-AlexNet (v0.1 heads), the package's own torch port
  (:mod:`retinexgs.evaluate.lpips`) with its shipped weights: no ``lpips`` package, no torchvision, no download.
  Computed in float32 on the given device (the CPU by default), unlike the float64 figures above.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import torch.nn.functional as F

from retinexgs.evaluate.lpips import lpips_distance, weights_available
from retinexgs.kth_value import kth_smallest
from retinexgs.model.tone import highlight_shoulder, linear_to_srgb, srgb_to_linear


__all__ = ["psnr", "ssim_metric", "gt_mean_align", "chroma_noise", "chroma_noises", "lpips_metric", "lpips_metrics",
           "lpips_available"]

ImageLike = Union[torch.Tensor, np.ndarray]


def check_bchw(*xs: torch.Tensor) -> None:
    """Raise unless every tensor is [B,C,H,W]."""
    for x in xs:
        if x.dim() != 4:
            raise ValueError(f"expected a [B,C,H,W] tensor, got shape {tuple(x.shape)}")


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype: torch.dtype = torch.float32,
                    device=None) -> torch.Tensor:
    """Normalised 1D Gaussian [size] centred on the middle tap."""
    r = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(r ** 2) / (2.0 * sigma ** 2))
    return (g / g.sum()).to(dtype=dtype, device=device)


# The losses' constant filter weights (the SSIM window, the noise mask) by what they are for, channels, dtype and
# device: built once, not every call (a training step would otherwise copy them to the GPU each time, and a
# captured CUDA graph cannot contain the host->device copy at all). Entries are never dropped: a captured graph
# reads them by address. They are tiny (a few numbers per channel).
CONSTANTS: Dict[tuple, Any] = {}


def cached_constant(key: tuple, build: Callable[[], Any]) -> Any:
    """``CONSTANTS[key]``, built by ``build()`` the first time."""
    w = CONSTANTS.get(key)
    if w is None:
        w = CONSTANTS[key] = build()
    return w


def gaussian_filter_weights(c: int, size: int, sigma: float, dtype: torch.dtype, device) -> Tuple[torch.Tensor, torch.Tensor]:
    """The (horizontal [c,1,1,k], vertical [c,1,k,1]) weights of the separable depthwise Gaussian filter."""
    def build() -> Tuple[torch.Tensor, torch.Tensor]:
        g = gaussian_window(size, sigma, dtype, device)
        return g.reshape(1, 1, 1, size).repeat(c, 1, 1, 1), g.reshape(1, 1, size, 1).repeat(c, 1, 1, 1)
    return cached_constant(("gauss", c, size, float(sigma), dtype, torch.device(device or "cpu")), build)


def gaussian_filter(x: torch.Tensor, size: int, sigma: float, pad: int) -> torch.Tensor:
    """Separable depthwise Gaussian filter of [B,C,H,W] with zero padding ``pad``."""
    if x.dtype == torch.float64:
        return _shifted_sums(x, size, sigma, pad)
    c = x.shape[1]
    wx, wy = gaussian_filter_weights(c, size, sigma, x.dtype, x.device)
    x = F.conv2d(x, wx, padding=(0, pad), groups=c)
    return F.conv2d(x, wy, padding=(pad, 0), groups=c)


def _shifted_sums(x: torch.Tensor, size: int, sigma: float, pad: int) -> torch.Tensor:
    """:func:`gaussian_filter` as weighted sums of shifted slices, for float64 (the evaluation's SSIM), where
    depthwise conv2d has no fast kernel: 1.2 s against 4.5 s for 15 channels at 1920x1080 on one CPU thread
    (2026-11-26), the same values (tests/test_metrics.py); on a GPU 22 elementwise passes."""
    if pad:
        x = F.pad(x, (pad, pad, pad, pad))
    g = gaussian_window(size, sigma, torch.float64).tolist()
    w = x.shape[-1] - size + 1
    rows = x[..., :w] * g[0]
    for k in range(1, size):
        rows.add_(x[..., k:k + w], alpha=g[k])
    h = x.shape[-2] - size + 1
    out = rows[..., :h, :] * g[0]
    for k in range(1, size):
        out.add_(rows[..., k:k + h, :], alpha=g[k])
    return out


def ssim(x: torch.Tensor, y: torch.Tensor, window: int = 11, sigma: float = 1.5, padding: str = "same",
         data_range: float = 1.0, reduction: str = "mean") -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) with a Gaussian window, per channel.

    SSIM = (2μxμy + C1)(2σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2)),
    C1 = (0.01·R)², C2 = (0.03·R)², where μ, σ², σxy are Gaussian-weighted local moments
    (population, not sample, covariance).

    Args:
        x, y: [B,C,H,W].
        window, sigma: Gaussian window size (odd) and standard deviation.
        padding: "same" = zero padding of window//2 (3DGS's training SSIM; the map has the input size)
                 or "valid" = no padding (the standard evaluation SSIM; needs H, W ≥ window).
        data_range: R, the dynamic range of the images (1 for [0,1]).
        reduction: "mean" (scalar over everything) or "none" (the SSIM map).
    """
    check_bchw(x, y)
    if x.shape != y.shape:
        raise ValueError(f"shape mismatch {tuple(x.shape)} vs {tuple(y.shape)}")
    if window % 2 != 1:
        raise ValueError("window must be odd")
    if padding not in ("same", "valid"):
        raise ValueError("padding must be 'same' or 'valid'")
    if padding == "valid" and min(x.shape[-2:]) < window:
        raise ValueError(f"image {tuple(x.shape[-2:])} smaller than the {window}x{window} window")
    pad = window // 2 if padding == "same" else 0
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    # The five local moments in two filter calls (4 convolutions instead of 10: training is launch-bound), split by
    # which input they depend on: in training y is the fixed target, so the backward filters only x's three moments
    # (9 of 15 channels for RGB) instead of all five; the filter is per channel, so the values are the same.
    mx, exx, exy = gaussian_filter(torch.cat([x, x * x, x * y], dim=1), window, sigma, pad).chunk(3, dim=1)
    my, eyy = gaussian_filter(torch.cat([y, y * y], dim=1), window, sigma, pad).chunk(2, dim=1)
    sxx = exx - mx * mx
    syy = eyy - my * my
    sxy = exy - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    if reduction == "none":
        return s
    if reduction == "mean":
        return s.mean()
    raise ValueError("reduction must be 'mean' or 'none'")


def _as_pair(x: ImageLike, y: ImageLike) -> Tuple[torch.Tensor, torch.Tensor]:
    x = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x).detach()
    y = torch.as_tensor(np.asarray(y) if not isinstance(y, torch.Tensor) else y).detach()
    if x.shape != y.shape:
        raise ValueError(f"shape mismatch {tuple(x.shape)} vs {tuple(y.shape)}")
    if x.dim() == 2:
        x, y = x[..., None], y[..., None]
    if x.dim() != 3:
        raise ValueError(f"expected [H,W,3] or [H,W] images, got shape {tuple(x.shape)}")
    # float64 on x's device: a test view's figures on the GPU that rendered it (a 12 MP view's took ~25 s on
    # the host's cores), on the CPU otherwise; the same values to float64 rounding.
    return x.to(torch.float64), y.to(x.device, torch.float64)


def psnr(x: ImageLike, y: ImageLike) -> float:
    """PSNR in dB of two [H,W,C] images in [0,1] (data range 1): 10·log10(1/MSE); inf when equal."""
    a, b = _as_pair(x, y)
    mse = float(((a - b) ** 2).mean())
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


def ssim_metric(x: ImageLike, y: ImageLike) -> float:
    """Evaluation SSIM of two [H,W,C] images in [0,1] (see the module docstring); H, W ≥ 11."""
    a, b = _as_pair(x, y)
    a = a.permute(2, 0, 1)[None]
    b = b.permute(2, 0, 1)[None]
    return float(ssim(a, b, window=11, sigma=1.5, padding="valid", data_range=1.0))


# Rec. 601 luma, the grey that the "GT-mean" convention's scaling is measured on (OpenCV's RGB -> GRAY).
_GREY = (0.299, 0.587, 0.114)


def gt_mean_align(x: ImageLike, y: ImageLike) -> torch.Tensor:
    """``x`` times the ratio of ``y``'s grey mean to ``x``'s, clipped to [0, 1]: a float64 tensor of ``x``'s shape,
    [H,W,3] (grey = Rec. 601 luma) or [H,W] / [H,W,1] (grey already).

    The "GT-mean" evaluation of low-light enhancement: one factor on the output's values, chosen with the truth,
    so that the two agree in overall brightness. What the aligned figures still measure is structure, colour and
    tone; what they drop is the exposure level, which a method trained on the dark photos alone cannot know (a
    normal-light photo's brightness is set by its photographer or camera). A black output (grey mean 0) stays
    black.
    """
    flat = np.ndim(x) == 2  # before _as_pair adds the channel axis; np.ndim also takes nested lists
    a, b = _as_pair(x, y)
    if a.shape[-1] not in (1, 3):
        raise ValueError(f"gt_mean_align needs RGB or grey images, got {a.shape[-1]} channels")
    w = torch.tensor(_GREY if a.shape[-1] == 3 else (1.0,), dtype=torch.float64, device=a.device)
    ma, mb = float((a * w).sum(-1).mean()), float((b * w).sum(-1).mean())
    if not (math.isfinite(ma) and math.isfinite(mb)):
        raise ValueError("gt_mean_align: the images hold non-finite values")
    out = a if ma <= 0.0 else (a * (mb / ma)).clamp(0.0, 1.0)
    return out[..., 0] if flat else out


# sRGB (linear, D65) -> CIE XYZ, and the D65 white, for the colour-error metric.
_RGB_TO_XYZ = ((0.4124564, 0.3575761, 0.1804375), (0.2126729, 0.7151522, 0.0721750), (0.0193339, 0.1191920, 0.9503041))
_D65 = (0.95047, 1.0, 1.08883)


def mean_colour_lab(x: ImageLike) -> Tuple[float, float, float]:
    """CIELAB (D65) of the average colour of an sRGB [H,W,3] image in [0,1]: the pixels averaged in linear light."""
    a, _ = _as_pair(x, x)
    if a.shape[-1] != 3:
        raise ValueError(f"mean_colour_lab needs an RGB image, got {a.shape[-1]} channels")
    return _lab_of_linear(srgb_to_linear(a, clip=False).reshape(-1, 3).mean(0))


def _lab_of_linear(lin: torch.Tensor) -> Tuple[float, float, float]:
    """CIELAB (D65) of one linear Rec.709 RGB colour [3] (float64)."""
    lin = lin.cpu()  # three numbers
    xyz = torch.tensor(_RGB_TO_XYZ, dtype=torch.float64) @ lin / torch.tensor(_D65, dtype=torch.float64)
    f = torch.where(xyz > (6 / 29) ** 3, xyz.clamp_min(0) ** (1 / 3), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return float(116 * f[1] - 16), float(500 * (f[0] - f[1])), float(200 * (f[1] - f[2]))


def black_lift(x: ImageLike, y: ImageLike, q: float = 0.01) -> float:
    """Issue 32's black-level measure: how far the blacks of ``x`` sit above the truth's ``y``, in linear light, once
    the exposure level is taken out. The ``q`` quantile (1st percentile) of each channel's linear values of ``x``
    after :func:`gt_mean_align` to ``y``, minus that of ``y``, averaged over the channels. Positive: lifted blacks
    (sensor noise clipped at black averages above the light, and a render that matches the photos' mean keeps
    that bias); negative: crushed blacks; 0 on a perfect render, whatever the exposure."""
    if not 0.0 <= q <= 1.0:
        raise ValueError(f"black_lift's quantile must lie in [0, 1], got {q}")
    a, b = _as_pair(gt_mean_align(x, y), y)

    def low(img: torch.Tensor) -> torch.Tensor:
        lin = srgb_to_linear(img, clip=False).reshape(-1, img.shape[-1])
        k = int(round(q * (lin.shape[0] - 1))) + 1  # the nearest rank: a k-th value has no size limit (quantile has)
        return kth_smallest(lin, k, dim=0)

    return float((low(a) - low(b)).mean())


def colour_error(x: ImageLike, y: ImageLike) -> float:
    """Issue 32's colour measure: the CIELAB ΔE (1976) between the average colours of ``x`` after
    :func:`gt_mean_align` to ``y`` and of ``y``. A colour cast shows in it; the exposure level does not."""
    lx, ly = mean_colour_lab(gt_mean_align(x, y)), mean_colour_lab(y)
    return math.sqrt(sum((p - q) ** 2 for p, q in zip(lx, ly)))


def _mean_colours(light: ImageLike, y: ImageLike, name: str) -> Tuple[torch.Tensor, torch.Tensor]:
    """The average linear colours [3] of a render's light and of the truth ``y`` (sRGB), checked finite."""
    a, b = _as_pair(light, y)
    if a.shape[-1] != 3:
        raise ValueError(f"{name} needs RGB images, got {a.shape[-1]} channels")
    mine, truth = a.reshape(-1, 3).mean(0), srgb_to_linear(b, clip=False).reshape(-1, 3).mean(0)
    if not bool(torch.isfinite(mine).all() and torch.isfinite(truth).all()):
        raise ValueError(f"{name}: the images hold non-finite values")
    return mine, truth


def _ratio(mine: torch.Tensor, truth: torch.Tensor) -> float:
    lum = torch.tensor(_RGB_TO_XYZ[1], dtype=torch.float64, device=mine.device)
    ya, yb = float(mine @ lum), float(truth @ lum)
    return ya / yb if yb > 0.0 else 0.0


def exposure_ratio(light: ImageLike, y: ImageLike) -> float:
    """How much brighter a render's linear light ``light`` ([H,W,3], unbounded) is than the truth ``y`` (sRGB in
    [0, 1]): the ratio of their mean luminances in linear light (Rec. 709 Y); 0 for a black render or truth."""
    return _ratio(*_mean_colours(light, y, "exposure_ratio"))


def colour_error_linear(light: ImageLike, y: ImageLike) -> float:
    """The colour of a render's linear light, with no tone between it and the truth: CIELAB ΔE (1976) between the
    average colour of ``light`` ([H,W,3] linear Rec.709, unbounded: the enhanced light before the highlight shoulder,
    the sRGB curve and the clip), scaled to the truth's mean luminance, and the average colour of the truth ``y``
    (sRGB in [0, 1]) in linear light.

    Why beside :func:`colour_error`: that one scores the encoded output, so it also holds what the tone does to the
    colours (a per-channel shoulder on a bright sky, the clip after the GT-mean scaling); a render whose light is
    exactly the truth's can score several ΔE there (:func:`tone_colour_floor`). Here only the light is scored."""
    mine, truth = _mean_colours(light, y, "colour_error_linear")
    return _linear_delta_e(mine, truth, _ratio(mine, truth))


def _linear_delta_e(mine: torch.Tensor, truth: torch.Tensor, ratio: float) -> float:
    scaled = mine / ratio if ratio > 0.0 else mine
    return math.sqrt(sum((p - q) ** 2 for p, q in zip(_lab_of_linear(scaled), _lab_of_linear(truth))))


def colour_split(light: ImageLike, y: ImageLike, knee: float) -> Dict[str, float]:
    """eval's split of the colour error for one view (the image means taken once): ``delta_e_linear``
    (:func:`colour_error_linear`), ``exposure_ratio`` (:func:`exposure_ratio`) and ``delta_e_tone_floor``
    (:func:`tone_colour_floor` at that exposure and the run's ``knee``)."""
    mine, truth = _mean_colours(light, y, "colour_split")
    ratio = _ratio(mine, truth)
    return {"delta_e_linear": _linear_delta_e(mine, truth, ratio), "exposure_ratio": ratio,
            "delta_e_tone_floor": tone_colour_floor(y, knee, ratio)}


def tone_colour_floor(y: ImageLike, knee: float, exposure: float = 1.0) -> float:
    """:func:`colour_error` of the truth ``y`` itself sent through a render's tone (linear light times ``exposure``,
    the highlight shoulder at ``knee``, the sRGB curve and its clip at white): what a render whose light were
    exactly the truth's, exposed ``exposure`` times brighter, would score. 0 at exposure 1 with knee ≥ 1 (the truth
    is already in [0, 1]). A truth whose highlights are clipped (a white sky) keeps them at 1 in every channel; the
    shoulder rolls them off one channel at a time, and a brighter exposure clips more of them."""
    a, _ = _as_pair(y, y)
    light = srgb_to_linear(a, clip=False).clamp_min(0.0) * float(exposure)
    return colour_error(linear_to_srgb(highlight_shoulder(light, knee)), a)


# chroma_noise's band of scales, in pixels, and the difference of Gaussians that measures it. The fine end is a 2-px
# period, one pixel's colour speckle: G(σ = 0.5) keeps it (its transfer exp(−2π²σ²f²) is 0.29 at the 2-px period)
# and passes 30 % of per-pixel white noise's energy; σ = 1 would pass 8 %, and speckle of 0.05 per sRGB channel
# (plainly visible) would score 1.1 instead of 1.6 (tests/test_chroma_noise.py's fixture). The coarse end is a blob
# 32 px across, G(σ = 16) (a blob ≈ 2σ): it keeps the low-frequency colour blotches of a noisy night render
# (issue 64) and drops a scene's broad colour regions and any cast.
CHROMA_BAND_PX = (2, 32)
CHROMA_SIGMA_FINE = 0.5
# Added to both band energies (CIELAB a*/b* units², summed over a* and b*): an RMS of 0.5 in each, about one 8-bit
# sRGB step of chroma and well below a visible difference (ΔE ≈ 2.3). A flat grey truth (energy 0) then divides by
# it instead of by zero, and a flat render of it scores 1; a photo's chroma detail (band energies 15, 114 and 210 on
# the first truth of LOM's sofa, buu and bike) barely feels it.
CHROMA_FLOOR = 0.5


def chroma_band_px(height: int, width: int) -> Tuple[int, int]:
    """The band of scales (finest, coarsest) in pixels that :func:`chroma_noise` measures on an ``height`` x ``width``
    image: :data:`CHROMA_BAND_PX` where the shorter side holds the coarsest scale twice (≥ 64 px), else its coarse end
    halved until it does (a shorter side of 32-63 px: 2-16 px; 16-31: 2-8; 8-15: 2-4). Below 8 px a ValueError."""
    fine, top = CHROMA_BAND_PX
    side = min(int(height), int(width))
    while top > 2 * fine and 2 * top > side:
        top //= 2
    if 2 * top > side:
        raise ValueError(f"chroma_noise needs images of at least {4 * fine}x{4 * fine} pixels, got {width}x{height}")
    return fine, top


def _image_tensor(x: ImageLike, name: str) -> torch.Tensor:
    """``x`` as a tensor (no copy where possible), refused in one line unless a floating [H,W,3] image."""
    t = x.detach() if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))
    if not t.is_floating_point():
        raise ValueError(f"chroma_noise needs float images in [0, 1], got {name} of dtype {t.dtype}")
    if t.dim() != 3 or t.shape[-1] != 3:
        raise ValueError(f"chroma_noise needs [H,W,3] RGB images, got {name} of shape {tuple(t.shape)}")
    return t


def _lab_ab(srgb: torch.Tensor) -> torch.Tensor:
    """CIELAB (D65) a*, b* [2,H,W] of an sRGB [H,W,3] image (per pixel, the same formulas as :func:`_lab_of_linear`)."""
    lin = srgb_to_linear(srgb, clip=False)
    m = torch.tensor(_RGB_TO_XYZ, dtype=srgb.dtype, device=srgb.device)
    xyz = (lin @ m.T / torch.tensor(_D65, dtype=srgb.dtype, device=srgb.device)).permute(2, 0, 1)
    f = torch.where(xyz > (6 / 29) ** 3, xyz.clamp_min(0) ** (1 / 3), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return torch.stack([500 * (f[0] - f[1]), 200 * (f[1] - f[2])])


def _fft_size(n: int) -> int:
    """The smallest m ≥ n whose only prime factors are 2, 3 and 5."""
    m = n
    while True:
        k = m
        for f in (2, 3, 5):
            while k % f == 0:
                k //= f
        if k == 1:
            return m
        m += 1


def _band_energy(planes: torch.Tensor, sigma_fine: float, sigma_coarse: float) -> float:
    """Σ over planes of the mean over pixels of (G_fine ∗ p − G_coarse ∗ p)², ``planes`` [N,H,W]. The Gaussians are
    applied in the frequency domain (transfer exp(−2π²σ²|f|²)) after a mirror padding of 3σ_coarse: the cost does not
    grow with σ (a 97-tap σ = 16 filter on a 12 MP view would take seconds on a CPU), and the mirror keeps the image's
    border from reading as a colour edge. The padded sides are then rounded up to a size of factors 2, 3 and 5 (a
    prime factor makes an FFT many times slower) by repeating the mirror's last row and column, over 3σ from any
    pixel kept. One plane at a time: a 12 MP view's padded spectra stay ~200 MB."""
    pad = int(math.ceil(3 * sigma_coarse))
    h, w = planes.shape[-2:]
    fh, fw = _fft_size(h + 2 * pad), _fft_size(w + 2 * pad)
    total = 0.0
    for p in planes:
        q = F.pad(p[None, None], (pad, pad, pad, pad), mode="reflect")
        q = F.pad(q, (0, fw - q.shape[-1], 0, fh - q.shape[-2]), mode="replicate")[0, 0]
        fy = torch.fft.fftfreq(q.shape[0], dtype=q.dtype, device=q.device)[:, None]
        fx = torch.fft.rfftfreq(q.shape[1], dtype=q.dtype, device=q.device)[None, :]
        f2 = (2 * math.pi ** 2) * (fy * fy + fx * fx)
        gain = torch.exp(-f2 * sigma_fine ** 2) - torch.exp(-f2 * sigma_coarse ** 2)
        band = torch.fft.irfft2(torch.fft.rfft2(q) * gain, s=q.shape)[pad:pad + h, pad:pad + w]
        total += float((band * band).mean())
    return total


def chroma_noises(xs: Sequence[ImageLike], y: ImageLike,
                  device: Optional[Union[str, torch.device]] = None) -> List[float]:
    """:func:`chroma_noise` of each image of ``xs`` against ``y``, the truth's band energy computed once (eval scores
    the render and the dark input against one truth)."""
    imgs = [_image_tensor(x, "the render") for x in xs]
    b = _image_tensor(y, "the truth")
    dev = torch.device(device) if device is not None else b.device
    for a in imgs:
        if a.shape != b.shape:
            raise ValueError(f"chroma_noise: shape mismatch {tuple(a.shape)} vs {tuple(b.shape)}")
    _, top = chroma_band_px(b.shape[0], b.shape[1])
    b = b.to(dev, torch.float64)
    grey = torch.tensor(_GREY, dtype=torch.float64, device=dev)

    def energy(img: torch.Tensor) -> float:
        if not bool(torch.isfinite(img).all()):
            raise ValueError("chroma_noise: the images hold non-finite values")
        return _band_energy(_lab_ab(img), CHROMA_SIGMA_FINE, top / 2)

    truth, mb, out = energy(b), float((b @ grey).mean()), []
    for a in imgs:
        a = a.to(dev, torch.float64)
        if not bool(torch.isfinite(a).all()):  # before the mean: a NaN would pass `ma > 0` unnoticed
            raise ValueError("chroma_noise: the images hold non-finite values")
        ma = float((a @ grey).mean())
        if ma > 0.0:  # gt_mean_align's rule, on this device: a black render stays black
            a = (a * (mb / ma)).clamp(0.0, 1.0)
        out.append((energy(a) + CHROMA_FLOOR) / (truth + CHROMA_FLOOR))
    return out


def chroma_noise(x: ImageLike, y: ImageLike, device: Optional[Union[str, torch.device]] = None) -> float:
    """Issue 64's colour-noise figure: how much chroma structure the render ``x`` holds at the scales of colour
    speckle and blotches, over what its truth ``y`` holds there. 1.0 = as much as the truth; per-pixel colour noise
    and low-frequency colour blotches score far above, a softer render a little below; a colour cast, the exposure
    level and luma noise barely move it. Lower is better down to 1.

    Precisely, for [H,W,3] sRGB images in [0, 1] (float; the same shape):

    1. ``x`` is brightness-aligned to ``y`` as :func:`gt_mean_align` does (one factor on its values so that the grey
       means agree, clipped to [0, 1]): the other GT-mean figures' convention, so that a dark render's chroma is not
       shrunk by its exposure (CIELAB chroma scales with brightness).
    2. Both go to CIELAB (D65, the sRGB curve and matrix); only a* and b* are kept (luma detail is not scored).
    3. Each of a*, b* is band-passed by a difference of Gaussians, σ = 0.5 minus σ = 16 px: structures from a 2-px
       period (single-pixel speckle) to blobs 32 px across (:data:`CHROMA_BAND_PX`; why σ = 0.5 and not 1 at the
       fine end: the comment above it). One DoG rather than a sum over octave bands: G₀.₅ − G₁₆ is exactly the sum of
       the octave band-passes G_s − G₂ₛ (s = 0.5 ... 8), so it measures the same band in two blurs with one energy
       (no overlap between neighbouring octaves counted twice). A constant (a cast's shift of a*) does not pass it.
       A view whose shorter side is below 64 px uses the scales that fit (:func:`chroma_band_px`: the coarse σ
       halved to 8, 4 or 2; below 8 px a ValueError). Borders are mirrored.
    4. The energy of an image is the band-passed a*² + b*², averaged over the pixels; the figure is
       (energy(x) + :data:`CHROMA_FLOOR`) / (energy(y) + :data:`CHROMA_FLOOR`): the floor keeps a flat grey truth
       from dividing by zero (a flat render of it scores 1, a speckled one its energy over the floor).

    ``device``: where it runs (default: ``y``'s device if a tensor, else the CPU), in float64 there. A bad shape,
    a non-float dtype or a non-finite value raises a one-line ValueError."""
    return chroma_noises([x], y, device)[0]


def lpips_available() -> Tuple[bool, str]:
    """Whether :func:`lpips_metric` can run: its weights ship with the package, so only a broken install lacks
    them; the reason when not."""
    return weights_available()


def _rgb_bchw(x: ImageLike) -> torch.Tensor:
    """[H,W,3] (or grey [H,W] / [H,W,1], repeated to RGB: the network takes three channels) -> [1,3,H,W]."""
    t = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x).detach()
    if t.dim() == 2:
        t = t[..., None]
    if t.dim() != 3 or t.shape[-1] not in (1, 3):
        raise ValueError(f"LPIPS needs [H,W,3] or [H,W] images, got shape {tuple(t.shape)}")
    return t.expand(*t.shape[:2], 3).permute(2, 0, 1)[None]


def lpips_metrics(xs: Sequence[ImageLike], y: ImageLike,
                  device: Optional[Union[str, torch.device]] = None) -> List[float]:
    """LPIPS-AlexNet of each [H,W,3] image of ``xs`` against ``y`` (all in [0,1], one size), in one batch: ``y``'s
    features are computed once. ``device``: where the network runs (default: ``y``'s device if a tensor, else the
    CPU). A bad shape or a value outside [0,1] raises a one-line ValueError."""
    if not xs:
        return []
    ref = _rgb_bchw(y)
    dev = torch.device(device) if device is not None else ref.device
    batch = [_rgb_bchw(x) for x in xs]
    if any(b.shape != ref.shape for b in batch):
        bad = next(b for b in batch if b.shape != ref.shape)
        raise ValueError(f"LPIPS: shape mismatch {tuple(bad.shape[-2:])} vs {tuple(ref.shape[-2:])}")
    # float32: the weights' own precision (an integer image becomes 0..255 and is refused as out of range)
    xb, yb = torch.cat([b.to(dev, torch.float32) for b in batch]), ref.to(dev, torch.float32)
    return [float(v) for v in lpips_distance(xb, yb, device=dev)]


def lpips_metric(x: ImageLike, y: ImageLike, device: Optional[Union[str, torch.device]] = None) -> float:
    """LPIPS-AlexNet distance of two [H,W,3] images in [0,1] (sides ≥ 31 pixels); 0 for identical images, lower is
    more similar. See :func:`lpips_metrics`."""
    return lpips_metrics([x], y, device)[0]
