"""What kind of capture a scene's views are: photos (JPEG, PNG, TIFF: display-referred, clipped to [0, 1]) or camera
raw files (the sensor's linear light, unclipped). :func:`retinexgs.data.load_scene` builds the scene's
:class:`Capture` (``scene.capture``) and callers ask it what differs between the two, instead of checking rawness
themselves: the highlight knee, the target as the photo it shows, the views' noise model, the denoiser's choice, the
target's encoding and which raw-only config keys apply (``loss.raw.*``, ``model.enhancement.raw.*``,
``decomposer.raw.*``; photo scenes read none of them)."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Sequence

from torch import Tensor

from retinexgs.config.schema import Decomposer, Enhancement, Loss
from retinexgs.data.images import is_raw_file
from retinexgs.data.raw_noise import RawNoise, scene_noise
from retinexgs.data.sensor import JpegCodec

# the photo path's noise measurement (retinexgs.train.noise.measure_capture_noise), passed in: it lives in train/
PhotoNoise = Callable[[Sequence[Path]], object]
# the photos' colour blotches (retinexgs.train.colour_blotches.previews_chroma_blotch of the views' files), passed in
ChromaBlotch = Callable[[], float]
# ``decomposer.denoise: auto`` denoises photos whose brightened previews' colour noise on 4×4-pixel averages has a σ
# above this (sRGB in [0, 1]): the simulated camera JPEGs of the raw ladder read 0.061-0.123 (1500-800 e-) and trained
# +0.04 to +0.35 SSIM with the denoiser; the photo scenes it cost read 0.039 (the demo: white pixel noise, 4x less in
# such averages; its 72 px views are also below what is read at all, colour_blotches.BLOTCH_MIN_SIDE) and 0.027 (strecha
# fountain-dark: -0.34 dB GT-mean, -0.020 SSIM over 3 seeds); LOM, fox-dark and castlep30-dark 0.004-0.010
# (experiments/notes/2026-11-29-photo-chroma-blotch.md).
PHOTO_BLOTCH_MIN = 0.05


class Capture:
    """The interface both kinds answer; a caller holds one and never asks which kind it is."""

    kind: str = ""
    unclipped: bool = False  # the views' values go beyond [0, 1] when read (their target is not clipped)

    @property
    def name(self) -> str:
        """``photo`` or ``raw``, for logs and messages."""
        return self.kind

    def as_photo(self, target: Tensor) -> Tensor:
        """``target`` as the photo it shows (values in [0, 1])."""
        raise NotImplementedError

    def encode_target(self, target: Tensor) -> Tensor:
        """A view's training target as stored (:meth:`retinexgs.data.scene.View.load_target`)."""
        raise NotImplementedError

    def knee(self, enh: Enhancement) -> float:
        """The highlight knee of a tone with one, from ``model.enhancement``."""
        raise NotImplementedError

    def spa_input(self, target: Tensor, loss: Loss) -> Tensor:
        """What L_spa compares the enhanced render with (``loss.raw.spa`` on a raw scene)."""
        raise NotImplementedError

    def r_prior_luma(self, loss: Loss, downscale: float = 1.0) -> float:
        """κ, the share of R̂'s luma the reflectance prior supervises (on a raw scene ``loss.raw.r_prior_luma``, or
        ``loss.raw.r_prior_luma_binned`` where ``downscale`` (``data.downscale``) bins the views; a photo's prior is
        the paper's, κ = 1)."""
        raise NotImplementedError

    def linear_mode(self, loss: Loss) -> Optional[str]:
        """The reconstruction in linear light (``loss.raw.mode``: noise or relative), or None: compared as photos."""
        raise NotImplementedError

    def noise(self, paths: Sequence[Path], photo_noise: Optional[PhotoNoise] = None) -> Optional[object]:
        """The views' noise model (var = a·y + b) from the files ``paths``: a raw scene's :class:`RawNoise` (the DNG
        NoiseProfile or the mosaic), a photo scene's from ``photo_noise`` (None without it); None: not measurable."""
        raise NotImplementedError

    def noise_downscale(self, downscale: float) -> float:
        """The ``data.downscale`` still to apply to :meth:`noise`'s model (1 where it was measured at that size)."""
        raise NotImplementedError

    def auto_denoise(self, blotch: Optional[ChromaBlotch] = None) -> str:
        """The denoiser ``decomposer.denoise: auto`` means for this capture; ``blotch``: the photos' colour blotches,
        measured when asked (a photo capture's choice depends on it; without it photos are left as they are)."""
        raise NotImplementedError

    def preview_denoise(self, dcfg: Decomposer) -> bool:
        """Whether the 2D priors come from a denoised linear preview (``decomposer.raw.preview_denoise``)."""
        raise NotImplementedError

    def jpeg_codec(self, path: Path) -> Optional[JpegCodec]:
        """The JPEG codec of the file ``path`` (None where there is none to simulate)."""
        raise NotImplementedError


class PhotoCapture(Capture):
    """Display-referred photos: already clipped, noise measured on the photos themselves (train/noise.py)."""

    kind = "photo"
    unclipped = False

    def as_photo(self, target: Tensor) -> Tensor:
        return target

    def encode_target(self, target: Tensor) -> Tensor:
        return target

    def knee(self, enh: Enhancement) -> float:
        return float(enh.shoulder)

    def spa_input(self, target: Tensor, loss: Loss) -> Tensor:
        return target

    def r_prior_luma(self, loss: Loss, downscale: float = 1.0) -> float:
        # the paper's prior: with its chroma alone LOM lost (bike −0.25 dB GT-mean, LPIPS up on all three;
        # experiments/notes/2026-11-30-r-prior-chroma.md §2): a photo's reconstruction does not measure the luma
        # without bias, as a raw scene's linear term does
        return 1.0

    def linear_mode(self, loss: Loss) -> Optional[str]:
        return None

    def noise(self, paths: Sequence[Path], photo_noise: Optional[PhotoNoise] = None) -> Optional[object]:
        return photo_noise(paths) if photo_noise is not None else None

    def noise_downscale(self, downscale: float) -> float:
        return 1.0  # the photos' noise is measured at the training resolution

    def auto_denoise(self, blotch: Optional[ChromaBlotch] = None) -> str:
        # Colour noise correlated over several pixels survives both the Gaussians' spatial average and the views'
        # average as blotches; white pixel noise does not, and the denoiser then costs detail (PHOTO_BLOTCH_MIN).
        return "chroma" if blotch is not None and blotch() > PHOTO_BLOTCH_MIN else "none"

    def preview_denoise(self, dcfg: Decomposer) -> bool:
        return False

    def jpeg_codec(self, path: Path) -> Optional[JpegCodec]:
        return JpegCodec.of_file(path)


class RawCapture(Capture):
    """Camera raw files: the sensor's linear light, unclipped (noise around black stays zero-mean; issue 52)."""

    kind = "raw"
    unclipped = True

    def as_photo(self, target: Tensor) -> Tensor:
        return target.clamp(0.0, 1.0)

    def encode_target(self, target: Tensor) -> Tensor:
        # float16: a relative step of 2⁻¹¹, far below a raw view's noise, and half the view store's bytes
        return target.half().float()

    def knee(self, enh: Enhancement) -> float:
        shoulder = enh.raw.shoulder  # null: the photos' knee
        return float(enh.shoulder if shoulder is None else shoulder)

    def spa_input(self, target: Tensor, loss: Loss) -> Tensor:
        return self.as_photo(target) if loss.raw.spa == "photo" else target

    def r_prior_luma(self, loss: Loss, downscale: float = 1.0) -> float:
        return float(loss.raw.r_prior_luma_binned if downscale > 1 else loss.raw.r_prior_luma)

    def linear_mode(self, loss: Loss) -> Optional[str]:
        return None if loss.raw.mode == "photo" else loss.raw.mode

    def noise(self, paths: Sequence[Path], photo_noise: Optional[PhotoNoise] = None) -> Optional[RawNoise]:
        return scene_noise(paths)  # never PIL's view of a raw file

    def noise_downscale(self, downscale: float) -> float:
        return float(downscale)  # measured on the full-size files

    def auto_denoise(self, blotch: Optional[ChromaBlotch] = None) -> str:
        return "chroma"  # +0.02..+0.21 SSIM on the raw ladder at 1000 e- (issue 64)

    def preview_denoise(self, dcfg: Decomposer) -> bool:
        return bool(dcfg.raw.preview_denoise)

    def jpeg_codec(self, path: Path) -> Optional[JpegCodec]:
        return None  # PIL does not read a DNG or CRW, and reads a NEF as its TIFF preview


PHOTO = PhotoCapture()
RAW = RawCapture()


def capture_of_files(paths: Sequence[Path]) -> Capture:
    """The capture of files ``paths``: raw when every one is a camera raw file (a split is all raw or none: the
    loader refuses a mix), else photo (also for no files)."""
    paths = list(paths)
    return RAW if paths and all(is_raw_file(Path(p)) for p in paths) else PHOTO
