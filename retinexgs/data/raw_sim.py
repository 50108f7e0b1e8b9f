"""A raw night-capture simulator: what a camera writes at night (a DNG) and its own JPEG of the same photons.

Issue #52, stage 2 (docs/raw.md, "The simulator"). The inverse camera pipeline follows the description in Brooks
et al., "Unprocessing Images for Learned Raw Denoising" (CVPR 2019); the steps, from a normal-light sRGB photo
``s`` to the raw value of one mosaic sample:

    lin   = srgb_to_linear(s) * g                 linear sRGB, times the colour cast g of SensorModel
    cam   = (M_cs @ lin) / wb                     camera RGB: M_cs = camera-from-sRGB with rows summing to 1
                                                  (white balanced camera white = sRGB white), then the inverse
                                                  of the as-shot white balance wb (R 2.0, G 1, B 1.6)
    m     = cam[CFA(i, j)] * k_v                  Bayer mosaic (stated CFA) at the view's exposure k_v
    e     = Poisson(m * W) + Normal(0, r^2)       electrons: full well W at raw 1, read noise r (SensorModel's)
    DN    = clip(round(black + e / W * (white - black)), 0, white)

``M_cs`` comes from the XYZ -> camera ColorMatrix of a Canon EOS Kiss X4 (550D) as its own DNG states it for
D65 (``CANON_KISS_X4_XYZ_TO_CAM``, read from ``shared/data/raw-samples/canon-kiss-x4-colorchart.dng``):
``M_cs = rownorm(ColorMatrix @ XYZ_from_sRGB)``, the same derivation as :func:`camera_raw._cam_to_srgb`, so a
reader that inverts it gets the sRGB back. The exposure model and its per-view jitter are SensorModel's
(``k_v = k (1 ± j)``), and W and r mean the same as in the JPEG ``darken``: the electrons of a sample at raw 1.

Only two clips happen, where a sensor clips: at white (saturation) and at 0 DN. The black level is placed far
enough above 0 DN (at least 6 read-noise sigmas) that the noise around black is kept whole: black-subtracted,
it is zero-mean. The DNG's NoiseProfile is that of the simulated noise in its normalised units
x = (DN - black) / (white - black): ``S = 1/W``, ``O = (r/W)^2 + 1/(12 (white - black)^2)`` (read noise plus the
rounding to DN), one pair for every plane (the noise is the sensor's; white balance comes later).

The forward "camera ISP" makes the JPEG beside each DNG from the SAME noisy mosaic: normalise, bilinear demosaic
at full size (so the JPEG has the photo's size and pairs with ``high/``), white balance, camera -> sRGB, clip to
[0, 1] (the clip at black that lifts a dark JPEG's shadows), sRGB curve, 8 bit, JPEG.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Dict, Optional, Tuple

import numpy as np

from retinexgs.data.camera_raw import (CFA_CHANNEL, XYZ_FROM_SRGB, demosaic_bilinear, demosaic_bilinear_reference,
                                       srgb_encode)
from retinexgs.data.srgb import srgb_to_linear
from retinexgs.data.dng import MIN_SIDE, write_dng
from retinexgs.errors import UserError

# XYZ -> camera RGB (D65) of a Canon EOS Kiss X4 / 550D, as the camera's DNG (raw-samples) states ColorMatrix1.
CANON_KISS_X4_XYZ_TO_CAM: Tuple[Tuple[float, float, float], ...] = (
    (0.6461, -0.1164, -0.0857), (-0.3825, 1.1597, 0.2534), (-0.0416, 0.1540, 0.6039))
CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
_BLACK_BASE = {12: 128, 14: 512}  # DN: typical blacks of 12- and 14-bit sensors (Sony/Nikon-like)
_BLACK_SIGMAS = 6.0  # the black sits at least this many read-noise sigmas above 0 DN: the noise is not clipped


@dataclass(frozen=True)
class RawCamera:
    """The simulated camera: what ``darken --raw`` states in each DNG and records in sensor.json.

    ``exposure_time`` of a view is ``normal_time * k_v``: at the fixed ``iso`` and ``f_number``, the time is
    proportional to the view's exposure, so the DNGs' EXIF gives each view's exposure relative to the others.
    """

    bits: int = 14
    cfa: str = "RGGB"
    xyz_to_cam: Tuple[Tuple[float, float, float], ...] = CANON_KISS_X4_XYZ_TO_CAM
    white_balance: Tuple[float, float, float] = (2.0, 1.0, 1.6)  # as-shot gains R, G, B (AsShotNeutral = 1/wb)
    iso: float = 3200.0
    f_number: float = 2.0
    normal_time: float = 1.0  # s: the exposure time of the normal-light photo (k_v = 1)
    make: str = "RetinexGS"
    model: str = "Simulated Canon EOS Kiss X4"

    def check(self) -> None:
        """UserError naming the option out of range."""
        if self.bits not in _BLACK_BASE:
            raise UserError(f"--bits must be 12 or 14 (the raw's bit depth), got {self.bits}")
        if self.cfa not in CFA_PATTERNS:
            raise UserError(f"--cfa must be one of {', '.join(CFA_PATTERNS)} (the Bayer pattern read from the "
                            f"top-left pixel), got {self.cfa!r}")

    @property
    def white_level(self) -> int:
        """The DN of saturation: the top of the bit depth."""
        return 2 ** self.bits - 1

    def black_level(self, full_well: Optional[float], read_noise: float) -> int:
        """The black in DN: the bit depth's usual black, raised so that it lies ``_BLACK_SIGMAS`` read-noise
        sigmas above 0 DN (the gain (white - black)/W is bounded by white/W, so the bound uses white).
        UserError when that black would take more than half of the range (a read noise no sensor has)."""
        base = _BLACK_BASE[self.bits]
        if full_well is None or read_noise <= 0:
            return base
        sigma_dn = read_noise / full_well * self.white_level
        black = max(base, int(math.ceil(_BLACK_SIGMAS * sigma_dn / 16.0)) * 16)  # a multiple of 16, as cameras
        if black > self.white_level // 2:
            raise UserError(f"--read-noise {read_noise:g} e- at --full-well {full_well:g} e- is "
                            f"{read_noise / full_well:.1%} of full scale: the raw's black level would need more "
                            f"than half of the {self.bits}-bit range to keep the noise unclipped; use a larger "
                            f"--full-well or a smaller --read-noise")
        return black

    def cam_from_srgb(self) -> np.ndarray:
        """[3, 3]: white-balanced camera RGB from linear sRGB, rows summing to 1 (sRGB white -> (1, 1, 1))."""
        m = np.asarray(self.xyz_to_cam, dtype=np.float64) @ XYZ_FROM_SRGB
        return m / m.sum(axis=1, keepdims=True)

    def cam_to_srgb(self) -> np.ndarray:
        """[3, 3]: linear sRGB from white-balanced camera RGB; the inverse of :meth:`cam_from_srgb` (what
        :func:`retinexgs.data.camera_raw.read_raw` derives from the DNG's ColorMatrix1)."""
        return np.linalg.inv(self.cam_from_srgb())

    def cfa_indices(self) -> np.ndarray:
        """[2, 2] channel index (0 R, 1 G, 2 B) of each position of the top-left quad."""
        return np.array([CFA_CHANNEL[c] for c in self.cfa]).reshape(2, 2)

    def as_shot_neutral(self) -> Tuple[float, float, float]:
        """The DNG's AsShotNeutral: the camera RGB of a neutral, 1 / white balance."""
        return tuple(1.0 / g for g in self.white_balance)  # type: ignore[return-value]

    def record(self, full_well: Optional[float], read_noise: float) -> Dict[str, object]:
        """The camera as sensor.json states it, with the derived levels and matrices."""
        black = self.black_level(full_well, read_noise)
        s, o = noise_profile(self, full_well, read_noise)
        return {**asdict(self), "xyz_to_cam": [list(r) for r in self.xyz_to_cam],
                "cam_to_srgb": np.round(self.cam_to_srgb(), 6).tolist(), "white_level": self.white_level,
                "black_level": black, "as_shot_neutral": list(self.as_shot_neutral()),
                "noise_profile": {"S": s, "O": o}, "demosaic": "bilinear, full size",
                "colour_matrix_source": "Canon EOS Kiss X4 (550D) DNG ColorMatrix1, D65"}


def noise_profile(camera: RawCamera, full_well: Optional[float], read_noise: float) -> Tuple[float, float]:
    """(S, O) of the DNG NoiseProfile: the variance of x = (DN - black)/(white - black) at signal x is S x + O.
    Shot noise S = 1/W, read noise (r/W)^2 plus the rounding to whole DN (1/12 DN^2). Noise-free: S = 0."""
    span = camera.white_level - camera.black_level(full_well, read_noise)
    rounding = 1.0 / (12.0 * span ** 2)
    if full_well is None:
        return 0.0, rounding
    return 1.0 / full_well, (read_noise / full_well) ** 2 + rounding


# ---- the inverse pipeline (sRGB -> raw) ----------------------------------------------------------------------

def unprocess(srgb: np.ndarray, camera: RawCamera, cast: Tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """float64 [H, W, 3]: the camera RGB (before white balance, exposure 1) of an sRGB photo [H, W, 3] in [0, 1]:
    sRGB -> linear, times the colour cast, -> white-balanced camera RGB, / as-shot white balance."""
    lin = srgb_to_linear(np.asarray(srgb, dtype=np.float64)) * np.asarray(cast, dtype=np.float64)
    cam = lin @ camera.cam_from_srgb().T
    return cam / np.asarray(camera.white_balance, dtype=np.float64)


def mosaic(rgb: np.ndarray, cfa: str) -> np.ndarray:
    """[H, W]: each pixel's own CFA channel of ``rgb`` [H, W, 3] (the pattern read from the top-left pixel)."""
    idx = np.array([CFA_CHANNEL[c] for c in cfa]).reshape(2, 2)
    h, w = rgb.shape[:2]
    chan = np.tile(idx, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    return np.take_along_axis(rgb, chan[..., None], axis=-1)[..., 0]


def capture_mosaic(srgb: np.ndarray, model, camera: RawCamera, k_view: float,
                   rng: Optional[np.random.Generator]) -> np.ndarray:
    """uint16 [H, W]: the raw DN mosaic a camera records of the normal-light sRGB photo ``srgb`` at exposure
    ``k_view`` with the noise of ``model`` (a :class:`retinexgs.data.sensor.SensorModel`; its full well None,
    or ``rng`` None, is noise-free). Clipped only at 0 DN and at white.

    The same numbers as :func:`capture_mosaic_reference`, bit for bit and with the same random draws, faster: the
    sRGB curve through a table of the photo's 8- or 16-bit codes (:func:`_srgb_to_linear_codes`), each CFA phase
    picked by slicing, and the arithmetic in place."""
    lin = _srgb_to_linear_codes(srgb)
    lin *= np.asarray(model.cast, dtype=np.float64)
    cam = lin @ camera.cam_from_srgb().T  # the reference's matmul as it is: its rounding is the reference's
    del lin
    cam /= np.asarray(camera.white_balance, dtype=np.float64)
    h, w = cam.shape[:2]
    signal = np.empty((h, w), dtype=np.float64)
    quad = camera.cfa_indices()
    for py in (0, 1):
        for px in (0, 1):
            signal[py::2, px::2] = cam[py::2, px::2, quad[py, px]]
    del cam
    signal *= k_view
    np.maximum(signal, 0.0, out=signal)  # no negative light (np.clip(x, 0, None) of the reference)
    if model.full_well is None or rng is None:
        x = signal
    else:
        signal *= model.full_well
        x = rng.poisson(signal).astype(np.float64)
        del signal
        x += rng.normal(0.0, model.read_noise, size=x.shape)
        x /= model.full_well
    black = camera.black_level(model.full_well, model.read_noise)
    x *= camera.white_level - black
    x += black  # black + x * span: the reference's order of operations (the sum is commutative, bit for bit)
    np.round(x, out=x)
    np.clip(x, 0, camera.white_level, out=x)
    return x.astype(np.uint16)  # where a real sensor clips: 0 DN and white


# The codes of 8- and 16-bit photos as read_image_float returns them (float32 code / levels) and their linear light.
_CODE_TABLES: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}


def _code_table(levels: int) -> Tuple[np.ndarray, np.ndarray]:
    if levels not in _CODE_TABLES:
        codes = np.arange(levels + 1, dtype=np.float32) / np.float32(levels)
        _CODE_TABLES[levels] = (codes, srgb_to_linear(codes.astype(np.float64)))
    return _CODE_TABLES[levels]


def _srgb_to_linear_codes(srgb: np.ndarray) -> np.ndarray:
    """float64 [H, W, 3]: ``srgb_to_linear(float64(srgb))``, a new array. A float32 photo that holds only the
    values of 8- or 16-bit codes (what :func:`retinexgs.data.images.read_image_float` returns for JPEG and PNG)
    goes through a table of the curve at those codes: the same numbers, without the power on every pixel (the
    most expensive step of a 12 MP view). Any other photo is converted as it is."""
    s = np.asarray(srgb)
    if s.dtype == np.float32 and s.size:
        for levels in (255, 65535):
            codes = np.rint(s * np.float32(levels))
            np.clip(codes, 0, levels, out=codes)  # NaN stays NaN: the check below refuses it
            idx = codes.astype(np.uint16)
            del codes
            table_in, table_out = _code_table(levels)
            if np.array_equal(table_in[idx], s):
                return table_out[idx]
    return srgb_to_linear(s.astype(np.float64))


def capture_mosaic_reference(srgb: np.ndarray, model, camera: RawCamera, k_view: float,
                             rng: Optional[np.random.Generator]) -> np.ndarray:
    """The plain definition of :func:`capture_mosaic` (the module docstring's steps on whole arrays): the
    reference its fast path must equal bit for bit (tests, ``bench darken``)."""
    signal = mosaic(unprocess(srgb, camera, model.cast), camera.cfa) * k_view
    signal = np.clip(signal, 0.0, None)  # no negative light (the matrix keeps in-gamut colours positive)
    if model.full_well is None or rng is None:
        x = signal
    else:
        electrons = rng.poisson(signal * model.full_well).astype(np.float64)
        electrons += rng.normal(0.0, model.read_noise, size=electrons.shape)
        x = electrons / model.full_well
    black = camera.black_level(model.full_well, model.read_noise)
    dn = np.round(black + x * (camera.white_level - black))
    return np.clip(dn, 0, camera.white_level).astype(np.uint16)  # where a real sensor clips: 0 DN and white


# ---- the forward camera ISP (raw -> the camera's JPEG) -------------------------------------------------------

def process(dn: np.ndarray, camera: RawCamera, black: float) -> np.ndarray:
    """float32 [H, W, 3] sRGB in [0, 1]: the camera's ISP of a raw DN mosaic: normalise (not clipped), bilinear
    demosaic, white balance, camera -> sRGB matrix, clip to [0, 1], sRGB curve. No brightening: the JPEG is as
    dark as the exposure made it, like the JPEG ``darken``. :func:`process_reference` bit for bit, with the
    demosaic of :func:`~retinexgs.data.camera_raw.demosaic_bilinear`."""
    x = (dn.astype(np.float64) - black) / (camera.white_level - black)
    rgb = demosaic_bilinear(x, camera.cfa)
    del x
    rgb *= np.asarray(camera.white_balance, dtype=np.float64)
    return srgb_encode(rgb @ camera.cam_to_srgb().T)  # srgb_encode clips to [0, 1]


def process_reference(dn: np.ndarray, camera: RawCamera, black: float) -> np.ndarray:
    """The plain definition of :func:`process`: the reference its fast path must equal bit for bit."""
    x = (dn.astype(np.float64) - black) / (camera.white_level - black)
    rgb = demosaic_bilinear_reference(x, camera.cfa) * np.asarray(camera.white_balance, dtype=np.float64)
    return srgb_encode(rgb @ camera.cam_to_srgb().T)  # srgb_encode clips to [0, 1]


def to_uint8(srgb: np.ndarray) -> np.ndarray:
    """uint8 [H, W, 3] of sRGB in [0, 1]."""
    return np.clip(np.round(np.asarray(srgb) * 255.0), 0, 255).astype(np.uint8)


def write_raw_view(path: Path, dn: np.ndarray, camera: RawCamera, model, k_view: float) -> Path:
    """Write one view's DN mosaic as a DNG with the camera's tags, the NoiseProfile of ``model`` and the EXIF
    exposure of ``k_view`` (time = normal_time * k_view at the fixed ISO and f-number)."""
    h, w = dn.shape
    if h < MIN_SIDE or w < MIN_SIDE:
        raise UserError(f"{path.name}: a photo of {w}x{h} pixels is too small for a DNG (raw readers need at "
                        f"least {MIN_SIDE}x{MIN_SIDE}); use larger photos")
    s, o = noise_profile(camera, model.full_well, model.read_noise)
    return write_dng(path, dn, cfa=camera.cfa, black_level=camera.black_level(model.full_well, model.read_noise),
                     white_level=camera.white_level, as_shot_neutral=camera.as_shot_neutral(),
                     color_matrix1=np.asarray(camera.xyz_to_cam), noise_profile=[s, o],
                     exposure_time=camera.normal_time * k_view, iso=camera.iso, f_number=camera.f_number,
                     make=camera.make, model=camera.model)
