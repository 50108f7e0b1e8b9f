"""The noise of a raw scene's views, in the units training compares them in (issue 52 stage 3b).

A raw view (:func:`retinexgs.data.camera_raw.view_srgb` with ``clip=False``) is linear light: the mosaic
normalised by its black and white levels, bilinear-demosaiced, times the white balance g, through the camera ->
sRGB matrix M, divided by its exposure factor f. A mosaic sample of colour j has variance a_j·x + b_j (the DNG
NoiseProfile, or :func:`retinexgs.data.camera_raw.estimate_noise` where the file has none). Carried through:

- white balance: v_j = g_j·x_j, so var(v_j) = g_j·a_j·v_j + g_j²·b_j;
- demosaic: a bilinear interpolation averages 2 or 4 samples at the pixels a colour is not sampled; over the 2×2
  pattern the mean variance is d_j = 0.5625 of a sample's for R and B, 0.625 for G;
- matrix: y_i = Σ_j M_ij·v_j, so var(y_i) = Σ_j M_ij²·var(v_j) (the channels' noise taken as independent). For a
  neutral pixel (all v_j equal to y, as M's rows sum to 1) this is exactly a_i'·y + b_i' with
  a_i' = Σ_j M_ij²·d_j·g_j·a_j and b_i' = Σ_j M_ij²·d_j·g_j²·b_j; a coloured pixel is approximated by it;
- exposure: y / f has variance (a'/f)·y + b'/f².

Only the shape of var(y) matters to the loss that uses it (its weights are normalised per image), so the
approximations above (independent channels, the mean demosaic factor) move weights, not what the fit converges to.
"""
from __future__ import annotations

import copy
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from retinexgs.data.camera_raw import (RawPhoto, estimate_noise, folder_exposure, noise_from_profile,
                                      normalised_mosaic, read_raw)
from retinexgs.data.noise_model import PoissonGaussian

__all__ = ["BILINEAR_VARIANCE", "RawNoise", "ViewNoise", "view_noise", "views_noise", "scene_noise",
           "combine_views", "DISAGREEMENT", "NOISE_VIEWS", "denoised_preview"]

# The mean variance of a bilinear-demosaiced channel over the 2×2 pattern, per sample's (R, G, B): R/B are sampled at
# 1 of 4 pixels, averaged over 2 at 2 of 4 and over 4 at 1 of 4 (1/4 + 2/4·1/2 + 1/4·1/4); G at 2 of 4 and over 4
# elsewhere (1/2 + 1/2·1/4).
BILINEAR_VARIANCE = np.array([0.5625, 0.625, 0.5625])

# A NoiseProfile whose variance at the photo's median signal is off its pixels' by more than this factor (either
# way) is not used. The estimator reads the real samples' profile-free noise within 30 % (docs/raw.md).
DISAGREEMENT = 2.0

# Views whose noise is read: spread evenly over the scene, as the capture-noise meter does.
NOISE_VIEWS = 5


@dataclass
class RawNoise(PoissonGaussian):
    """A raw scene's view noise (the noise protocol, :mod:`retinexgs.data.noise_model`): var(y) ≈ a·y + b per channel (R, G, B) of the views' linear light; ``source``:
    "profile" (the DNG NoiseProfile), "estimate" (measured on the mosaic) or "mixed"; ``notes``: one line each
    for what the user should know (a profile not used, a view without a usable estimate)."""
    a: Tuple[float, float, float]
    b: Tuple[float, float, float]
    source: str
    notes: List[str] = field(default_factory=list)

    def describe(self) -> str:
        """One line for the log."""
        a = ", ".join(f"{v:.3g}" for v in self.a)
        b = ", ".join(f"{v:.3g}" for v in self.b)
        return f"raw views' noise ({self.source}): var = a·y + b, a = ({a}), b = ({b})"


def _to_view(a: np.ndarray, b: np.ndarray, photo: RawPhoto, factor: float) -> Tuple[np.ndarray, np.ndarray]:
    """Per-sample (a, b) of the mosaic -> the view's linear light (module docstring)."""
    g = photo.white_balance.astype(np.float64)
    m2 = photo.cam_to_srgb.astype(np.float64) ** 2
    a_v = m2 @ (BILINEAR_VARIANCE * g * a)
    b_v = m2 @ (BILINEAR_VARIANCE * g * g * b)
    return a_v / factor, b_v / factor ** 2


def _variance_at(a: np.ndarray, b: np.ndarray, x: float) -> np.ndarray:
    return a * x + b


def view_noise(photo: RawPhoto, factor: float = 1.0) -> Tuple[Optional[np.ndarray], Optional[np.ndarray], str,
                                                                 Optional[str]]:
    """(a, b, source, note) of one raw photo in its view's linear light at exposure ``factor``: from its
    NoiseProfile unless that disagrees with the pixels' own estimate by over :data:`DISAGREEMENT` at the photo's
    median signal (then the estimate, and a note naming the file); (None, None, "none", note) when neither gives
    a finite model."""
    est_a, est_b = estimate_noise(photo)
    est_a, est_b = np.maximum(est_a, 0.0), np.maximum(est_b, 0.0)  # a variance model never falls below zero
    est_ok = bool(np.all(np.isfinite(est_a)) and np.all(np.isfinite(est_b)))
    prof = noise_from_profile(photo)
    note = None
    if prof is not None:
        pa, pb = prof
        if est_ok:
            x = max(float(np.median(normalised_mosaic(photo))), 0.0)
            ratio = _variance_at(pa, pb, x) / np.maximum(_variance_at(est_a, est_b, x), 1e-30)
            if np.any(ratio > DISAGREEMENT) or np.any(ratio < 1.0 / DISAGREEMENT):
                note = (f"{photo.path}: its NoiseProfile disagrees with its pixels (variance "
                        f"{np.round(ratio, 2).tolist()} times the measured one at signal {x:.3g}): the measured "
                        "noise is used")
                a, b = _to_view(est_a, est_b, photo, factor)
                return a, b, "estimate", note
        a, b = _to_view(np.asarray(pa, np.float64), np.asarray(pb, np.float64), photo, factor)
        return a, b, "profile", None
    if est_ok:
        a, b = _to_view(est_a, est_b, photo, factor)
        return a, b, "estimate", None
    return None, None, "none", f"{photo.path}: too little flat area to measure its noise; not used for the model"


@dataclass
class ViewNoise:
    """One raw photo's noise as :func:`view_noise` gives it (a, b None when neither source gives a finite model);
    ``black``: every mosaic sample at or below the black level (a lens-cap frame written without read noise), whose
    view is all zero."""
    path: Path
    a: Optional[np.ndarray]
    b: Optional[np.ndarray]
    source: str
    note: Optional[str]
    black: bool = False


def views_noise(paths: Sequence[Path], views: int = NOISE_VIEWS, progress: bool = False) -> List[ViewNoise]:
    """:class:`ViewNoise` of up to ``views`` of ``paths`` (spread evenly, the ones :func:`scene_noise` reads), each
    at its view's exposure factor within its folder; ``progress``: a bar on stderr (a large raw file takes a second
    or two)."""
    from tqdm import tqdm

    paths = [Path(p) for p in paths]
    chosen = paths[::max(1, len(paths) // views)][:views]
    # One view per thread (LibRaw's decoding and numpy release the GIL): the same figures as one at a time, in
    # about the time of one view on as many cores. Errors come in the views' order.
    workers = max(1, min(len(chosen), 8, (os.cpu_count() or 1) - 1))
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="retinexgs-raw-noise") as pool:
        done = pool.map(_one_view_noise, chosen)
        return [v for v in tqdm(done, total=len(chosen), desc="raw noise", unit="photo", disable=not progress,
                                dynamic_ncols=True)]


def _one_view_noise(p: Path) -> ViewNoise:
    """:class:`ViewNoise` of the raw file ``p`` at its exposure factor within its folder."""
    factor = folder_exposure(p.parent).factors.get(p.name, 1.0)
    photo = read_raw(p)
    black = not bool(np.any(normalised_mosaic(photo) > 0))
    a, b, source, note = view_noise(photo, factor)
    return ViewNoise(p, a, b, source, note, black)


def combine_views(measured: Sequence[ViewNoise]) -> Optional[RawNoise]:
    """:class:`RawNoise` of the views ``measured``: per channel the median of their (a, b); None when no view gives
    a model."""
    got = [v for v in measured if v.a is not None and v.b is not None]
    notes = [v.note for v in measured if v.note]
    if not got:
        return None
    a = np.maximum(np.median(np.stack([v.a for v in got]), axis=0), 0.0)
    # a variance floor: never a zero weight's inverse
    b = np.maximum(np.median(np.stack([v.b for v in got]), axis=0), 1e-12)
    sources = {v.source for v in got}
    source = sources.pop() if len(sources) == 1 else "mixed"
    return RawNoise(tuple(float(v) for v in a), tuple(float(v) for v in b), source, notes)


def scene_noise(paths: Sequence[Path], views: int = NOISE_VIEWS) -> Optional[RawNoise]:
    """:class:`RawNoise` of a raw scene from up to ``views`` of its files (spread evenly): per channel the median
    of the views' (a, b), each at its view's exposure factor. None when no view gives a model.

    Measured once per process while the files are unchanged (keyed by each file's path, inode, size and times):
    training asks for it twice with the 2D priors on (the denoiser's noise, then the linear reconstruction's), a
    second decode and fit of each measured view for the same figures. A copy is returned."""
    paths = [Path(p) for p in paths]
    try:
        key = (int(views), tuple(_file_key(p) for p in paths))
    except OSError:  # a missing file: measured (and refused, naming it) as before, never remembered
        return combine_views(views_noise(paths, views))
    with _SCENE_LOCK:
        if key not in _SCENE_NOISE:
            _SCENE_NOISE.clear()  # one scene's figures at a time: a process trains one scene
            _SCENE_NOISE[key] = combine_views(views_noise(paths, views))
        return copy.deepcopy(_SCENE_NOISE[key])


_SCENE_NOISE: Dict[tuple, Optional[RawNoise]] = {}
_SCENE_LOCK = threading.Lock()


def _file_key(p: Path) -> tuple:
    """What changes when the file ``p`` is replaced (resolved path, inode, size, mtime, ctime)."""
    st = p.stat()
    return (str(p.resolve()), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


# ---- the 2D priors' photo -----------------------------------------------------------------------------------------

# The denoiser's window: (2r + 1)² pixels. 4: 9×9 at a raw view's full size (fox-dark at 1000 e⁻, one view: SSIM of the
# exposed preview 0.09 clipped, 0.24 at r = 2, 0.38 at 4, 0.45 at 6; the dark regions' lift 8×, 4×, 3×, 2.7× the light).
PREVIEW_RADIUS = 4


def denoised_preview(image: "torch.Tensor", radius: int = PREVIEW_RADIUS) -> "torch.Tensor":
    """The photo a raw view's 2D priors (LR3M) are computed on: float32 [H,W,3] sRGB in [0, 1] from the view's
    unclipped encoding ``image`` (:func:`retinexgs.data.srgb.linear_to_srgb_extended`).

    In linear light, before any clip, each channel goes through a local Wiener filter (the guided filter's form, He
    et al., with the channel as its own guide): in each window the gain is the share of its variance that exceeds
    the channel's noise variance (measured on the view itself), so flat windows become their mean and windows that
    vary well above the noise (edges) are kept. Then the clip and the sRGB curve.

    Why before the clip: the noise of a dark raw view is zero-mean around the light, so a mean keeps the light; a
    clip first lifts every dark pixel's average by a share of σ, and LR3M's R and L of such a photo carry that lift
    (and the noise) into the priors that pull R̂ and L̂."""
    import torch
    import torch.nn.functional as F

    from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear_extended

    lin = srgb_to_linear_extended(image.float()).permute(2, 0, 1).contiguous()
    h, w = lin.shape[-2:]
    r = int(min(radius, (min(h, w) - 1) // 2))
    if r < 1 or min(h, w) < 3:
        return linear_to_srgb(lin.clamp(0.0, 1.0)).permute(1, 2, 0).contiguous()
    def box(x):
        return F.avg_pool2d(F.pad(x[None], (r, r, r, r), mode="reflect"), 2 * r + 1, 1)[0]

    mean = box(lin)
    var = (box(lin * lin) - mean * mean).clamp_min(0.0)
    # The noise variance: the median of the windows' variances (most windows of a dark view are flat). Measured on
    # windows, not by a pixel-scale mask: the demosaic correlates neighbouring pixels' noise, which a 3×3 mask
    # (Immerkær's) reads far below its variance.
    eps = var.reshape(var.shape[0], -1).median(dim=-1).values.reshape(-1, 1, 1)
    a = (var - eps).clamp_min(0.0) / var.clamp_min(1e-12)  # the window's signal share of its variance (Wiener)
    out = box(a) * lin + box(mean - a * mean)
    return linear_to_srgb(out.clamp(0.0, 1.0)).permute(1, 2, 0).contiguous()
