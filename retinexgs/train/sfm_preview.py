"""The denoiser SfM's previews of dark photos go through (``sfm --denoise``; issue 62 item 3, issue 64 item 5).

:func:`retinexgs.data.sfm.run_sfm` brightens dark photos (and always raw files) into copies that COLMAP extracts
features from. At night (a 1000 e⁻ capture, SNR near 1) the brightened noise buries the texture SIFT needs: SfM
registered 2 of 25 of buu's raw night captures. Here the noise-aware denoiser of :mod:`retinexgs.retinex.denoise`
(generalised Anscombe transform + ``chroma`` or ``nlm``) is put in front of the brightening. It lives in a layer
above ``data``, and the photos' noise is measured by :mod:`retinexgs.train.noise`, so this module, on the training
layer, builds the :class:`retinexgs.data.sfm.PreviewDenoise` that ``run_sfm`` is handed: for ``retinexgs sfm`` and
for the SfM that ``train`` runs on a bare folder (``data.sfm_denoise``, :func:`scene_sfm_denoise`).

``auto`` (the default) is ``chroma`` where the brightened previews are noisy (:data:`AUTO_MIN_SIGMA`) and a noise
model can be measured (each raw file's own, or the capture's for other photos), ``none`` otherwise; a named method
whose noise model cannot be measured is refused (one line).
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Callable, List, Optional, Sequence, Union

import numpy as np

from retinexgs.errors import UserError

if TYPE_CHECKING:  # a type hint only: data.sfm is imported where a denoiser is built
    from retinexgs.data.sfm import PreviewDenoise

# The choices of ``--denoise``; ``auto``'s method where the noise can be measured (chroma: the luma by NLM, the
# colour smoothed hard along its edges, the denoiser's default for raw views in training too).
CHOICES = ("auto", "none", "nlm", "chroma")
AUTO_METHOD = "chroma"
# ``auto`` denoises only where the brightened previews' noise σ (luma, sRGB in [0, 1], read on 2×2 averages, the median
# of up to PROBE_PHOTOS photos) is above this: there the noise buries SIFT's features; below it the denoiser costs more
# texture than it removes noise. Measured: buu and fox-dark at 1000 e⁻, camera JPEGs 0.10–0.13 (SfM 2/25 and 2/50
# without the denoiser, 25/25 and 37/50 with it); fox-dark's own photos 0.058–0.063 and tests/test_data.py's dark
# synthetic scene (2000 e⁻) 0.044, where the denoised previews gave SfM about half the points of the plain ones.
AUTO_MIN_SIGMA = 0.08
PROBE_PHOTOS = 5
SIGMA_SCALE = 2


def check_denoise(method: str) -> str:
    """``method`` when it is one of :data:`CHOICES`, else UserError (one line)."""
    if method not in CHOICES:
        raise UserError(f"--denoise must be one of {', '.join(CHOICES)} (default auto: {AUTO_METHOD} where the "
                        f"photos' noise can be measured), got {method!r}")
    return method


def preview_recipe(method: str, photo_noise=None) -> str:
    """12 hex digits naming a preview denoising recipe: the method, the denoiser's settings and version, and the
    photos' noise model (raw files: each file's own, a function of its content, which the cache already keys)."""
    from retinexgs.retinex.denoise import DENOISE_VERSION, DenoiseParams

    noise = None if photo_noise is None else [[f"{float(v):.6g}" for v in part] for part in photo_noise]
    text = json.dumps({"method": method, "params": asdict(DenoiseParams()), "version": DENOISE_VERSION,
                       "photo_noise": noise}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def linear_denoiser(method: str) -> Callable[[np.ndarray, Sequence[float], Sequence[float]], np.ndarray]:
    """(linear RGB float32 [H,W,3], a, b) -> that light denoised by ``method`` under ``var = a·y + b``."""
    import torch

    from retinexgs.retinex.denoise import denoise_linear, noise_model

    def apply(lin: np.ndarray, a: Sequence[float], b: Sequence[float]) -> np.ndarray:
        out = denoise_linear(torch.from_numpy(np.ascontiguousarray(lin, np.float32)), noise_model((a, b)), method)
        return out.numpy().astype(np.float32, copy=False)

    return apply


def _photo_noise(paths: List[Path]):
    """(a, b) of the photos' linear light (:func:`retinexgs.train.noise.measure_capture_noise`, full size), or None
    when it cannot be measured (no photo, all black, no shot noise read)."""
    from retinexgs.train.noise import measure_capture_noise

    try:
        noise = measure_capture_noise(paths)
    except UserError:  # an all-black photo: nothing to measure
        return None
    if noise is None or not np.all(np.isfinite(noise.a + noise.b)) or not any(v > 0 for v in noise.a):
        return None
    return tuple(noise.a), tuple(noise.b)


def _bright_sigma(path: Path, raw: bool) -> float:
    """The noise σ of the brightened preview of ``path`` without a denoiser (its luma, sRGB in [0, 1], on 2×2
    averages): a raw file brightened by the raw preview's rule, a photo by the enhancement's."""
    import torch

    from retinexgs.data.enhance import auto_exposure
    from retinexgs.data.images import read_image
    from retinexgs.data.sfm import _bright_preview
    from retinexgs.retinex.denoise import measured_sigma

    if raw:
        from retinexgs.data.camera_raw import _demosaiced_srgb_linear, read_raw

        bright = _bright_preview(_demosaiced_srgb_linear(read_raw(path)), percentile=99.0, target=0.9)
    else:
        bright = auto_exposure(read_image(path))
    luma = bright.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32) / 255.0
    if min(luma.shape) < 3:  # too small for the 3×3 estimate: no noise read, so auto leaves it alone
        return 0.0
    return measured_sigma(torch.from_numpy(luma).double(), SIGMA_SCALE)


def probed(paths: Sequence[Path], photos: int = PROBE_PHOTOS) -> List[Path]:
    """Up to ``photos`` of ``paths``, spread evenly: the photos a capture-wide reading looks at."""
    return list(paths)[::max(1, len(paths) // photos)][:photos]


def previews_noise_sigma(paths: Sequence[Path], raw: bool, photos: int = PROBE_PHOTOS) -> float:
    """The median of :func:`_bright_sigma` over up to ``photos`` of ``paths``, spread evenly."""
    return float(np.median([_bright_sigma(p, raw) for p in probed(paths, photos)]))


def sfm_preview_denoise(images: Union[str, Path], method: str = "auto", enhance: Union[str, bool] = "auto",
                        say: Optional[Callable[[str], None]] = None):
    """The :class:`retinexgs.data.sfm.PreviewDenoise` for ``run_sfm`` on the photos in ``images`` (None: the previews
    are not denoised): ``method`` "none", or photos that get no enhanced copy (a bright folder under ``enhance``
    "auto", or ``enhance`` off), or "auto" where the brightened previews' noise σ is at most :data:`AUTO_MIN_SIGMA`
    or the photos' noise cannot be measured. UserError for an unknown
    method, or a named one whose photos' noise cannot be measured. Raw files are measured one by one as their
    previews are made (a file whose noise cannot be measured keeps its plain preview)."""
    from retinexgs.data.enhance import folder_is_dark
    from retinexgs.data.images import list_images
    from retinexgs.data.sfm import PreviewDenoise, raw_jpeg_pairs

    check_denoise(method)
    if method == "none":
        return None
    folder = Path(images)
    if not folder.is_dir():
        return None  # run_sfm names the problem
    paths = list_images(folder)
    try:
        pairs = raw_jpeg_pairs(paths)
    except UserError:
        return None  # run_sfm refuses the folder with the same line
    chosen = AUTO_METHOD if method == "auto" else method
    if pairs:  # RAW + JPEG: SfM reads the JPEGs
        paths = sorted(pairs.values(), key=lambda p: p.name)
    if pairs != {} and (enhance is False or enhance == "off" or (enhance == "auto" and not folder_is_dark(paths))):
        return None  # photos that get no enhanced copy (raw files alone always get a preview)
    if len(paths) < 2:
        return None
    if method == "auto":
        sigma = previews_noise_sigma(paths, raw=pairs == {})
        if sigma <= AUTO_MIN_SIGMA:
            return None
        if say:
            say(f"the brightened previews' noise σ is {sigma:.3f} (above {AUTO_MIN_SIGMA}): denoising them ({chosen})")
    if pairs == {}:  # raw files only: each preview under its own file's noise model
        return PreviewDenoise(f"{chosen}-{preview_recipe(chosen)}", linear_denoiser(chosen))
    noise = _photo_noise(paths)
    if noise is None:
        if method == "auto":
            return None
        raise UserError(f"--denoise {method}: the noise of the photos in {folder} could not be measured (no flat area, "
                        f"or all black): pass --denoise none or auto")
    return PreviewDenoise(f"{chosen}-{preview_recipe(chosen, noise)}", linear_denoiser(chosen), noise)


def scene_sfm_denoise(method: str, say: Optional[Callable[[str], None]] = None
                      ) -> Optional[Callable[[Path], Optional["PreviewDenoise"]]]:
    """``data.sfm_denoise`` as :func:`retinexgs.data.load_scene` takes it: (the SfM photo folder) -> the
    :class:`retinexgs.data.sfm.PreviewDenoise` of :func:`sfm_preview_denoise` (the rule of ``sfm --denoise``, with
    the enhancement's ``auto``, as ``train`` runs SfM); None for ``none`` (the previews as before the key)."""
    check_denoise(method)
    if method == "none":
        return None
    return lambda images: sfm_preview_denoise(images, method, "auto", say)
