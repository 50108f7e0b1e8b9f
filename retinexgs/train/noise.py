"""The capture's sensor noise, measured from its own training photos at set-up, and what training does with it
(issue 32; a config switch with its reason in configs/default.yaml):

- ``loss.rec_noise_floor``: the reconstruction term's SSIM compares the render with the photo at an exposure
  (:func:`retinexgs.train.losses.exposed`, gain 1 / lin(L_ref)). That gain is capped where the exposed photos'
  noise reaches SSIM's own stabilising constant, σ = K2 = 0.03 on a [0, 1] range: above the cap the SSIM would
  ask the render to copy each view's noise, which a 3D model can only do by growing Gaussians for it (speckle in
  every novel view). On a clean capture (LOM: σ < 0.01 at the full gain) nothing changes.

Measured on :data:`MEASURED_VIEWS` training photos spread over the capture, as the camera wrote them (the user's
files, a central crop of at most :data:`CROP` pixels a side): undistortion and resizing interpolate between pixels,
which hides noise from a 3×3 estimate (fountain-dark's σ reads 0.6× through OpenCV's undistortion) but not from
SSIM's 11×11 window. Per photo, :func:`retinexgs.data.sensor.estimate_noise` (``var = a·y + b`` per channel in
linear light) and the exposed noise σ (Immerkær on 2×2 averages, the largest channel: :func:`exposed_noise_sigma`)
at each gain of :data:`GAINS`; the capture's
figures are the medians over the photos, divided by ``data.downscale`` (a d×d average divides white noise's σ by d).
Through 8-bit JPEG the pixel-scale (a, b) sees 0.15–0.9 of the true σ, least near black
(experiments/notes/2026-11-26-noise-estimate.md); the exposed σ on 2×2 averages sees 0.94–1.19 of it. Where (a, b)
itself is reported (``retinexgs noise``), the (a, b) of JPEG files is fitted through their own JPEG
(``through_codec``, :func:`retinexgs.data.sensor.estimate_noise_through_codec`; 512² crops, about 2 s a photo on a
CPU core), since the clipped noise's mean, which lifts the blacks, passes JPEG whole.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from retinexgs.data.capture import capture_of_files
from retinexgs.data.images import read_image_for_part
from retinexgs.data.sensor import JpegCodec, NoiseEstimate, estimate_noise, estimate_noise_through_codec
from retinexgs.data.noise_model import PoissonGaussian
from retinexgs.errors import UserError
from retinexgs.train.losses import exposed, noise_variance

MEASURED_VIEWS = 8
CROP = 1024
CODEC_CROP = 512  # the JPEG-aware fit re-encodes its crop 8 times: a smaller one (~2 s a photo on a CPU core)
# Exposure gains at which the exposed noise is measured: 1 to 256 in half stops (a scene's gain 1 / lin(L_ref) is
# 2–60 on the dev scenes); the cap is interpolated between them, log-linearly.
GAINS: Tuple[float, ...] = tuple(2.0 ** (k / 2.0) for k in range(17))
NOISE_SCALE = 2  # the noise is measured on 2×2 averages of the photo (exposed_noise_sigma)
SSIM_K2 = 0.03  # SSIM's C2 = (K2 · range)², range 1: the noise σ at which the noise variance equals C2


def sigma_limit(share: float) -> float:
    """The exposed noise σ at which a flat patch of the render loses ``share`` of SSIM's structure term to the
    photo's noise: cs = C2 / (C2 + σ²) = 1 − share, so σ = K2 · √(share / (1 − share)). share 0.5: σ = K2."""
    if not 0.0 < share < 1.0:
        raise ValueError(f"the noise share must lie in (0, 1), got {share}")
    return SSIM_K2 * math.sqrt(share / (1.0 - share))


@dataclass(frozen=True)
class CaptureNoise(PoissonGaussian):
    """A capture's noise (the noise protocol, :mod:`retinexgs.data.noise_model`): per channel ``var = a·y + b`` in linear light at the training images' resolution, and the
    exposed photos' noise σ at each of ``gains``; ``downscale``: the d by which the training images are smaller than
    the photos (d × d averages: a and b are the photos' ÷ d²)."""

    a: Tuple[float, float, float]
    b: Tuple[float, float, float]
    gains: Tuple[float, ...]
    sigma: Tuple[float, ...]
    views: int
    downscale: float = 1.0

    def gain_cap(self, limit: float = SSIM_K2) -> float:
        """The largest exposure gain at which the exposed photos' noise σ is at most ``limit`` (log-linear
        between the measured gains); inf when even the largest measured gain stays below it."""
        if self.sigma[0] > limit:
            return self.gains[0]
        for k in range(1, len(self.gains)):
            if self.sigma[k] > limit:
                s0, s1 = (math.log(max(v, 1e-12)) for v in (self.sigma[k - 1], self.sigma[k]))
                t = (math.log(limit) - s0) / (s1 - s0) if s1 > s0 else 0.0
                return math.exp(math.log(self.gains[k - 1]) + t * (math.log(self.gains[k]) - math.log(self.gains[k - 1])))
        return math.inf

    def at_capture(self) -> Tuple[Tuple[float, ...], Tuple[float, ...]]:
        """(a, b) of the photos as the camera recorded them, before any downscale. The clip at black happens there,
        pixel by pixel, and averaging keeps the clipped mean: the camera's mean record (black's lift, which
        ``retinexgs noise`` reports) is a function of this noise, not of the averaged images' smaller one."""
        d2 = float(self.downscale) ** 2
        return tuple(v * d2 for v in self.a), tuple(v * d2 for v in self.b)

    def state_dict(self) -> Dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_state(cls, state: Dict) -> "CaptureNoise":
        return cls(tuple(state["a"]), tuple(state["b"]), tuple(state["gains"]), tuple(state["sigma"]),
                   int(state["views"]), float(state.get("downscale", 1.0)))  # type: ignore[arg-type]

    def describe(self, limit: float = SSIM_K2, gain: Optional[float] = None) -> str:
        """One line for the training log (the cap at noise σ ``limit``; ``gain``: the scene's own exposure gain,
        1 / lin(L_ref), which the cap applies to only when it is lower)."""
        sig = ", ".join(f"{math.sqrt(max(a * 0.01 + b, 0.0)):.4f}" for a, b in zip(self.a, self.b))
        cap = self.gain_cap(limit)
        scene = "" if gain is None else f", the scene's gain {gain:.2f}"
        return (f"capture noise (median of {self.views} views): σ at linear 0.01 = {sig} (R, G, B); exposed SSIM "
                f"gain capped at {'none' if math.isinf(cap) else f'{cap:.2f}'} (noise σ ≤ {limit:.4f}{scene})")


def exposed_noise_sigma(S: Tensor, gains: Tuple[float, ...] = GAINS, scale: int = NOISE_SCALE) -> List[float]:
    """The noise σ of one photo ``S`` [H,W,3] (sRGB, [0,1]) exposed by each gain (the largest channel's), as SSIM
    sees it: Immerkær's estimate on the photo averaged over ``scale`` × ``scale`` pixels, times ``scale`` (the
    factor by which such an average divides white noise's σ).

    Why not at the pixel scale: JPEG's quantisation removes the finest frequencies of the noise, not the noise
    at the 2–5 px scale that SSIM's window (Gaussian, σ 1.5 px) and a Gaussian splat fit. On photos darkened by
    the sensor model, with the noise known, the pixel-scale estimate read 0.22–0.37 of the SSIM-visible σ at 8000
    and 3000 e⁻, 0.49–0.57 at 1500 e⁻; averaged over 2×2 pixels it reads 0.94–1.19 at every level and gain
    (experiments/notes/2026-11-26-noise-scale.md)."""
    x = S.detach().float().permute(2, 0, 1).unsqueeze(0)
    if min(x.shape[-2:]) < 3 * scale:  # too small to average: the pixel scale
        scale = 1

    def pooled(y: Tensor) -> Tensor:
        return F.avg_pool2d(y, scale) if scale > 1 else y

    # One host sync for all the gains.
    sigma = torch.stack([noise_variance(pooled(exposed(x, x.new_tensor(g)))).amax().sqrt() * scale for g in gains])
    return sigma.tolist()


def centre_crop(photo: np.ndarray, size: int = CROP, align: int = 1) -> np.ndarray:
    """The central ``size`` × ``size`` pixels of [H,W,3] (all of a side that is shorter), its corner on a multiple of
    ``align`` (16: on the JPEG's block grid, so a re-encoding of the crop quantises the same blocks)."""
    h, w = photo.shape[:2]
    top, left = (max(0, (n - size) // 2) // align * align for n in (h, w))
    return photo[top:top + size, left:left + size]


class NoiseMeter:
    """Gathers :class:`CaptureNoise` from the photos given to :meth:`add` (module docstring)."""

    def __init__(self, device: torch.device = torch.device("cpu"), scale: int = NOISE_SCALE,
                 through_codec: bool = False) -> None:
        self.device = torch.device(device)
        self.through_codec = bool(through_codec)  # (a, b) of JPEG photos fitted with the JPEG's loss modelled
        self.scale = int(scale)  # exposed_noise_sigma's averaging (loss.rec_noise_scale)
        self._a: List[Tuple[float, ...]] = []
        self._b: List[Tuple[float, ...]] = []
        self._sigma: List[List[float]] = []

    def add(self, photo: np.ndarray, codec: Optional[JpegCodec] = None,
            estimate: Optional[NoiseEstimate] = None) -> None:
        """One photo [H,W,3] in sRGB [0,1] as the camera wrote it (cropped here); smaller than 8×8: skipped.
        ``codec``: the JPEG it was written with, for the JPEG-aware (a, b) (``through_codec``). ``estimate``: what
        :meth:`estimate` gave for the same photo and codec (computed on a reading thread), else computed here."""
        photo = np.asarray(photo, dtype=np.float32)
        if photo.ndim != 3 or photo.shape[0] < 8 or photo.shape[1] < 8:
            return
        est = self.estimate(photo, codec) if estimate is None else estimate
        self._a.append(est.a)
        self._b.append(est.b)
        self._sigma.append(exposed_noise_sigma(torch.from_numpy(np.ascontiguousarray(centre_crop(photo)))
                                               .to(self.device), scale=self.scale))

    def estimate(self, photo: np.ndarray, codec: Optional[JpegCodec] = None) -> Optional[NoiseEstimate]:
        """The (a, b) fit :meth:`add` takes of one photo (numpy only, no state: safe on another thread); None for a
        photo :meth:`add` skips."""
        photo = np.asarray(photo, dtype=np.float32)
        if photo.ndim != 3 or photo.shape[0] < 8 or photo.shape[1] < 8:
            return None
        codec_est = None
        if self.through_codec and codec is not None:
            try:
                codec_est = estimate_noise_through_codec(centre_crop(photo, CODEC_CROP, align=16).astype(np.float64),
                                                         codec)
            except (OSError, ValueError):  # a JPEG that Pillow reads but cannot write back as it was: as it is
                codec_est = None
        return codec_est if codec_est is not None else estimate_noise(centre_crop(photo))

    def result(self, downscale: float = 1.0) -> Optional[CaptureNoise]:
        """The medians over the photos, for training images ``downscale`` times smaller; None without photos."""
        if not self._sigma:
            return None
        d = float(downscale)
        a = tuple(float(v) / (d * d) for v in np.median(np.array(self._a), axis=0))
        b = tuple(float(v) / (d * d) for v in np.median(np.array(self._b), axis=0))
        sigma = tuple(float(v) / d for v in np.median(np.array(self._sigma), axis=0))
        return CaptureNoise(a, b, GAINS, sigma, len(self._sigma), d)  # type: ignore[arg-type]


def check_not_black(photo: np.ndarray, path: Path) -> None:
    """UserError naming ``path`` when its photo [H,W,3] is all zero (black): it holds no noise to measure (every fit
    would read a = b = 0, an infinite full well). The same refusal ``train`` gives such a photo (its decomposition)."""
    if not bool(np.any(np.asarray(photo) > 0)):
        raise UserError(_black_reason(path))


def _black_reason(path: Path) -> str:
    return f"cannot measure the noise of {path}: the photo is all zero (black): there is nothing to measure"


def jpeg_codec(path: Path) -> Optional[JpegCodec]:
    """The JPEG codec of ``path`` (:meth:`JpegCodec.of_file`); None for a camera raw file, which is never opened with
    PIL: PIL does not read a DNG or CRW (UnidentifiedImageError), and reads a NEF as a TIFF preview."""
    return capture_of_files([path]).jpeg_codec(path)


def measure_capture_noise(photos: Sequence[Path], downscale: float = 1.0, device: torch.device = torch.device("cpu"),
                          views: int = MEASURED_VIEWS, scale: int = NOISE_SCALE,
                          through_codec: bool = False, progress: bool = False) -> Optional[CaptureNoise]:
    """:class:`CaptureNoise` of up to ``views`` of ``photos`` (the user's files), spread evenly over them;
    ``through_codec``: (a, b) of JPEG files fitted with their JPEG's loss of noise modelled
    (:func:`retinexgs.data.sensor.estimate_noise_through_codec`); ``progress``: a bar on stderr (a few seconds
    per photo through the codec)."""
    from tqdm import tqdm

    photos = list(photos)
    meter = NoiseMeter(device, scale, through_codec)
    chosen = photos[::max(1, len(photos) // views)][:views]
    # The photos are read on threads (decoding and numpy release the GIL), measured here in their order: the same
    # figures as reading them one at a time, in about the time of one on as many cores.
    workers = max(1, min(len(chosen), 8, (os.cpu_count() or 1) - 1))

    def read(p: Path) -> Tuple[np.ndarray, bool, Optional[JpegCodec], Optional[NoiseEstimate]]:
        photo, lit = _measured_photo(p)
        codec = jpeg_codec(p) if through_codec else None
        return photo, lit, codec, meter.estimate(photo, codec) if lit else None

    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="retinexgs-noise") as pool:
        done = pool.map(read, chosen)
        for p in tqdm(chosen, desc="noise", unit="photo", disable=not progress, dynamic_ncols=True):
            photo, lit, codec, est = next(done)
            if not lit:
                raise UserError(_black_reason(p))
            meter.add(photo, codec, est)
    return meter.result(downscale)


def _measured_photo(path: Path) -> Tuple[np.ndarray, bool]:
    """(what :meth:`NoiseMeter.add` measures of the photo ``path``, whether any of its values is above 0): a camera
    raw view encoded only in the centre crop the meter reads (:func:`retinexgs.data.images.read_image_for_part`),
    another photo whole (its JPEG-aware fit crops it on the block grid)."""
    return read_image_for_part(path, centre_crop)


__all__ = ["CaptureNoise", "NoiseMeter", "measure_capture_noise", "exposed_noise_sigma", "centre_crop",
           "check_not_black", "jpeg_codec", "GAINS",
           "SSIM_K2", "NOISE_SCALE", "MEASURED_VIEWS", "CROP", "sigma_limit"]
