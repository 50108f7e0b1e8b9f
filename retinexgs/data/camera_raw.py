"""Camera RAW photos: reading the sensor's mosaic and its metadata, linear values, a preview, the noise model.

Stage 1 of issue #52 (see docs/raw.md): nothing here is wired into scene loading or training yet.

- :func:`read_raw` reads a Bayer raw file that LibRaw (rawpy) reads: DNG, CRW, CR2, NEF, ARW and others.
  Bad input (a missing, truncated or corrupt file, a format LibRaw cannot read, an X-Trans or Foveon sensor)
  raises one :class:`~retinexgs.errors.UserError` naming the file. TIFF-based files are checked (header, IFDs,
  image data inside the file) before LibRaw sees them, so a truncated file is refused, not read as zeros.
- :func:`linear_rgb`: black-subtracted, normalised by (white - black), NOT clipped at zero, 2x2-binned.
- :func:`exposure_scale`: each view's exposure relative to the scene's median.
- :func:`preview_srgb`: a viewable 8-bit preview for pose estimation.
- :func:`noise_from_profile` / :func:`estimate_noise`: the noise model var = a*x + b from the DNG NoiseProfile,
  or estimated from the pixels.

Units: "normalised linear" means x = (raw - black) / (white - black) for one mosaic sample; this is also the unit
of the DNG NoiseProfile, so its (S, O) are used as they are.
"""
from __future__ import annotations

import contextlib
import logging
import struct
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from retinexgs.data.srgb import linear_to_srgb
from retinexgs.errors import UserError
# Raw types that scene loading accepts as photos (listing, reading, SfM): those whose cameras LibRaw reads as a 2x2
# Bayer mosaic, kept with every other readable type in retinexgs.formats (the one list). Compared in lower case.
from retinexgs.formats import BAYER_RAW_EXTENSIONS  # noqa: F401 (the name colmap and images import from here)

# Raw types LibRaw reads that later stages will accept; compared in lower case.
RAW_EXTENSIONS = (".dng", ".crw", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf",
                  ".rw2", ".pef", ".srw", ".3fr", ".iiq", ".erf", ".mrw", ".kdc", ".dcr", ".mos", ".x3f")
# Raw types that are plain TIFF files (header II*\0 or MM\0*): their structure is checked before LibRaw.
TIFF_RAW_EXTENSIONS = (".dng", ".cr2", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".pef", ".3fr", ".erf", ".kdc",
                       ".dcr", ".mos", ".iiq")
# GoPro's raw photos (.gpr): DNGs whose mosaic is VC-5 coded (TIFF compression 9), which LibRaw decodes only when
# built with GoPro's SDK, as rawpy's wheels are not. Recognised (by name, or by that compression in a renamed file)
# to say so in one line instead of "no photos" or LibRaw's "unsupported file format".
GPR_EXTENSIONS = (".gpr",)
_VC5_COMPRESSION = 9
GPR_ADVICE = ("GoPro GPR is a DNG variant compressed with VC-5, which LibRaw (rawpy) cannot decode; convert it to a "
              "plain DNG first, e.g. with GoPro's gpr_tools: gpr_tools -i IN.GPR -o OUT.DNG")
MIN_RAW_BYTES = 1024  # no real raw file is smaller; random junk this small is refused before LibRaw
_MAX_IFDS = 64
_TYPE_SIZES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 13: 4, 16: 8}
_D65 = 21
# linear sRGB (D65) -> XYZ, the standard matrix (IEC 61966-2-1)
XYZ_FROM_SRGB = np.array([[0.4124564, 0.3575761, 0.1804375],
                          [0.2126729, 0.7151522, 0.0721750],
                          [0.0193339, 0.1191920, 0.9503041]])
_LETTERS = "RGB"


@dataclass
class RawPhoto:
    """One camera raw photo as read by :func:`read_raw`.

    ``mosaic``: the visible CFA mosaic, uint16 [H, W] (H, W even: an odd last row/column is dropped).
    ``cfa``: 2x2 channel indices (0 R, 1 G, 2 B) of the top-left quad; ``cfa_pattern``: the same as "RGGB".
    ``black_level``: float32 [2, 2], the black of each CFA position; ``black_map``: float32 [H, W] when the file
    has a black that varies per pixel beyond the CFA (DNG BlackLevelRepeatDim / BlackLevelDeltaH/V), else None.
    ``white_level``: the raw value of saturation.
    ``white_balance``: camera white balance as shot, gains for R, G, B with G = 1 (DNG: 1 / AsShotNeutral).
    ``xyz_to_cam``: camera RGB from XYZ (3x3) or None; ``cam_to_srgb``: white-balanced camera RGB -> linear
    sRGB (3x3), rows summing to 1 so that white stays white (identity when the matrix is unknown).
    ``exposure_time`` (s), ``iso``, ``f_number``: None when the metadata lacks them.
    ``noise_profile``: DNG NoiseProfile as float64 [3, 2] (S, O per colour R, G, B) or None.
    ``notes``: what was assumed or where a value came from, for the user.
    """
    path: Path
    mosaic: np.ndarray
    cfa: np.ndarray
    cfa_pattern: str
    black_level: np.ndarray
    white_level: float
    white_balance: np.ndarray
    cam_to_srgb: np.ndarray
    xyz_to_cam: Optional[np.ndarray] = None
    black_map: Optional[np.ndarray] = None
    exposure_time: Optional[float] = None
    iso: Optional[float] = None
    f_number: Optional[float] = None
    noise_profile: Optional[np.ndarray] = None
    make: str = ""
    model: str = ""
    notes: List[str] = field(default_factory=list)

    @property
    def shape(self) -> Tuple[int, int]:
        """(H, W) of the mosaic."""
        return tuple(self.mosaic.shape)  # type: ignore[return-value]

    def exposure(self) -> Optional[float]:
        """time x ISO / f-number^2 when all three are known, else None."""
        if None in (self.exposure_time, self.iso, self.f_number):
            return None
        return self.exposure_time * self.iso / self.f_number ** 2


# ----------------------------------------------------------------------------------------------------------
# TIFF structure: a small reader of IFDs, used to check a file before LibRaw and to read DNG tags LibRaw hides

class _Corrupt(Exception):
    """The file's TIFF structure is broken; the message says how."""


class _Tiff:
    """The IFDs of a TIFF file (IFD0's chain and the SubIFDs below them), read with bounds checks."""

    def __init__(self, path: Path, size: int):
        self.path, self.size = path, size
        head = self._read(0, 8)
        if head[:4] == b"II*\0":
            self.e = "<"
        elif head[:4] == b"MM\0*":
            self.e = ">"
        else:
            raise _Corrupt("its header is not a TIFF header (II*/MM*), as this raw type must have")
        self.ifds: List[Dict[int, Tuple[int, int, int, bytes]]] = []
        seen = set()
        todo = [struct.unpack(self.e + "I", head[4:8])[0]]
        while todo:
            off = todo.pop(0)
            if off == 0 or off in seen:
                continue
            if len(self.ifds) >= _MAX_IFDS:
                raise _Corrupt(f"more than {_MAX_IFDS} image directories")
            seen.add(off)
            ifd, nxt = self._ifd(off)
            self.ifds.append(ifd)
            todo.append(nxt)
            if 330 in ifd:  # SubIFDs: where DNG and NEF keep the raw image
                todo.extend(int(v) for v in self.values(ifd[330]))

    def _read(self, off: int, n: int) -> bytes:
        if off < 0 or off + n > self.size:
            raise _Corrupt(f"it ends at byte {self.size} but its structure points to bytes {off}..{off + n} "
                           f"(the file is truncated or corrupt)")
        with open(self.path, "rb") as f:  # opened per read: tags are read after the check, file closed between
            f.seek(off)
            return f.read(n)

    def _ifd(self, off: int):
        n = struct.unpack(self.e + "H", self._read(off, 2))[0]
        raw = self._read(off + 2, 12 * n + 4)
        ifd = {}
        for i in range(n):
            tag, typ, count = struct.unpack(self.e + "HHI", raw[12 * i:12 * i + 8])
            ifd[tag] = (typ, count, off + 2 + 12 * i + 8, raw[12 * i + 8:12 * i + 12])
        return ifd, struct.unpack(self.e + "I", raw[12 * n:12 * n + 4])[0]

    def values(self, entry) -> list:
        """The values of one entry as Python numbers (rationals as floats); [] for unknown types."""
        typ, count, _, inline = entry
        size = _TYPE_SIZES.get(typ)
        if size is None:
            return []
        nbytes = size * count
        if nbytes > self.size:
            raise _Corrupt(f"a tag claims {count} values, more than the file holds")
        data = inline[:nbytes] if nbytes <= 4 else self._read(struct.unpack(self.e + "I", inline)[0], nbytes)
        e = self.e
        if typ in (1, 7):
            return list(data)
        if typ == 2:
            return [data.split(b"\0")[0].decode("latin-1")]
        fmt = {3: "H", 4: "I", 6: "b", 8: "h", 9: "i", 11: "f", 12: "d", 13: "I", 16: "Q"}
        if typ in fmt:
            return list(struct.unpack(f"{e}{count}{fmt[typ]}", data))
        pairs = struct.unpack(f"{e}{2 * count}{'i' if typ == 10 else 'I'}", data)
        return [pairs[2 * i] / pairs[2 * i + 1] if pairs[2 * i + 1] else float("nan") for i in range(count)]

    def get(self, ifd, tag: int, default=None):
        return self.values(ifd[tag]) if tag in ifd else default

    def check_image_data(self) -> None:
        """Every strip and tile lies inside the file; the raw image's uncompressed data is all there."""
        for ifd in self.ifds:
            for offs_tag, counts_tag in ((273, 279), (324, 325)):
                if offs_tag not in ifd:
                    continue
                offs, counts = self.get(ifd, offs_tag), self.get(ifd, counts_tag, [])
                if len(counts) != len(offs):
                    raise _Corrupt("its image data table is inconsistent (offsets and byte counts differ)")
                for o, c in zip(offs, counts):
                    if o + c > self.size:
                        raise _Corrupt(f"its image data runs to byte {o + c} but the file has only {self.size} "
                                       f"bytes (the file is truncated: copy it again from the camera or card)")
                if self.get(ifd, 259, [1])[0] == 1 and 256 in ifd and 257 in ifd and 258 in ifd:
                    need = self.get(ifd, 256)[0] * self.get(ifd, 257)[0] * self.get(ifd, 258)[0] // 8
                    need *= self.get(ifd, 277, [1])[0]
                    if sum(counts) < need and offs_tag == 273:
                        raise _Corrupt(f"its uncompressed image needs {need} bytes but holds {sum(counts)}")

    def raw_ifd(self):
        """The IFD of the full-resolution CFA image (NewSubfileType 0, photometric CFA), or None."""
        for ifd in self.ifds:
            if self.get(ifd, 262, [0])[0] == 32803 and self.get(ifd, 254, [0])[0] == 0:
                return ifd
        return None


# ----------------------------------------------------------------------------------------------------------
# reading

def _check_path(path: Path) -> int:
    if not path.exists():
        raise UserError(f"{path}: no such file (check the path)")
    if not path.is_file():
        raise UserError(f"{path} is not a file (a camera raw file is needed here)")
    size = path.stat().st_size
    if size < MIN_RAW_BYTES:
        raise UserError(f"{path}: {size} bytes is too small for a camera raw file (it is truncated or not a raw "
                        f"photo); copy it again from the camera or card")
    return size


def _open_tiff(path: Path, size: int) -> Optional[_Tiff]:
    """The TIFF structure of a TIFF-based raw, checked; None for other formats (LibRaw checks those). UserError
    for a GoPro GPR (:data:`GPR_ADVICE`), by name or by its VC-5 compression."""
    if path.suffix.lower() in GPR_EXTENSIONS:
        raise UserError(f"{path}: {GPR_ADVICE}")
    with open(path, "rb") as f:
        magic = f.read(4)
        is_tiff = magic in (b"II*\0", b"MM\0*")
        if not is_tiff and path.suffix.lower() not in TIFF_RAW_EXTENSIONS:
            if path.suffix.lower() == ".crw":
                f.seek(6)
                if magic[:2] not in (b"II", b"MM") or f.read(8) != b"HEAPCCDR":
                    raise UserError(f"{path}: not a Canon CRW file (its header lacks HEAPCCDR); the file is "
                                    f"corrupt or misnamed")
            return None
        try:
            tiff = _Tiff(path, size)
            if any(tiff.get(ifd, 259, [1])[0] == _VC5_COMPRESSION for ifd in tiff.ifds):  # a GPR renamed .dng
                raise UserError(f"{path}: {GPR_ADVICE}")
            tiff.check_image_data()
        except (_Corrupt, struct.error, UnicodeDecodeError) as exc:
            raise UserError(f"{path}: not a readable {path.suffix.upper().lstrip('.') or 'raw'} file: {exc}") \
                from None
        return tiff


def _libraw_reason(exc: Exception) -> str:
    import rawpy
    text = str(exc).strip("b'\"")
    if isinstance(exc, rawpy.LibRawFileUnsupportedError):
        return f"LibRaw does not read this format, or it is not a camera raw file ({text})"
    if isinstance(exc, (rawpy.LibRawIOError, getattr(rawpy, "LibRawDataError", rawpy.LibRawIOError))):
        return f"the file is truncated or corrupt ({text})"
    if isinstance(exc, getattr(rawpy, "LibRawTooBigError", ())):
        return f"the image is too big for LibRaw's memory limit ({text})"
    return text or type(exc).__name__


@contextlib.contextmanager
def _quiet_exifread() -> Iterator[None]:
    """exifread logs warnings about odd tags at WARNING level: they are not the user's concern here."""
    log = logging.getLogger("exifread")
    old = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        log.setLevel(old)


def _exif_number(tags: dict, names: Sequence[str]) -> Tuple[bool, Optional[float]]:
    """(found, value) for the first of ``names`` exifread found; value None when zero, negative or broken."""
    for name in names:
        if name in tags:
            try:
                v = tags[name].values[0]
                v = float(v.num) / float(v.den) if hasattr(v, "num") else float(v)
            except (IndexError, ValueError, ZeroDivisionError, TypeError, AttributeError):
                return True, None
            return True, (v if np.isfinite(v) and v > 0 else None)
    return False, None


def _exposure_from(tags: dict, other, notes: List[str]) -> Tuple[Optional[float], Optional[float], Optional[float]]:
    """(exposure time, ISO, f-number) from exifread's ``tags`` (TIFF-based raws); from LibRaw's ``other``
    (rawpy's ImageOther, or None) where exifread finds no EXIF (e.g. Canon CRW), with a note saying so."""
    found_t, t = _exif_number(tags, ("EXIF ExposureTime", "Image ExposureTime"))
    found_f, fn = _exif_number(tags, ("EXIF FNumber", "Image FNumber"))
    found_i, iso = _exif_number(tags, ("EXIF ISOSpeedRatings", "EXIF PhotographicSensitivity",
                                       "Image ISOSpeedRatings"))
    if not (found_t or found_f or found_i) and other is not None:
        t = float(other.shutter_speed) if other.shutter_speed > 0 else None
        fn = float(other.aperture) if other.aperture > 0 else None
        iso = float(other.iso_speed) if other.iso_speed > 0 else None
        if any(v is not None for v in (t, fn, iso)):
            notes.append("exposure read by LibRaw (no EXIF block that exifread reads in this format)")
    return t, iso, fn


def _read_exif(path: Path) -> dict:
    import exifread
    try:
        with _quiet_exifread(), open(path, "rb") as f:
            return exifread.process_file(f, details=False)
    except Exception:  # exifread raises many kinds on odd files; the metadata is then taken from LibRaw
        return {}


def _cam_to_srgb(xyz_to_cam: np.ndarray) -> np.ndarray:
    """White-balanced camera RGB -> linear sRGB: camera-from-sRGB with rows scaled to sum to 1 (so sRGB white
    is camera (1,1,1) after white balance), inverted; the inverse's rows then sum to 1 as well."""
    cam_from_srgb = xyz_to_cam @ XYZ_FROM_SRGB
    cam_from_srgb = cam_from_srgb / cam_from_srgb.sum(axis=1, keepdims=True)
    return np.linalg.inv(cam_from_srgb)


def _dng_black_map(tiff: _Tiff, ifd, h: int, w: int, quad_only: bool = False) -> Optional[np.ndarray]:
    """The per-pixel black of a DNG ([h, w], relative to its active area) from BlackLevelRepeatDim, BlackLevel
    and BlackLevelDeltaH/V, or None when the file has none of them. ``quad_only``: also None when the map
    certainly repeats every 2x2 quad (a finite pattern whose repeat divides 2x2, no deltas used), which
    :func:`read_raw` would find by comparing the full map with its tiled quad (a 12 MP float64 map and its
    comparison: about 0.4 s a read, for the same answer)."""
    if not any(t in ifd for t in (50714, 50715, 50716)):
        return None
    rd = [int(v) for v in tiff.get(ifd, 50713, [1, 1])]
    bl = np.asarray(tiff.get(ifd, 50714, [0.0]), dtype=np.float64)
    if len(rd) != 2 or min(rd) < 1 or bl.size < rd[0] * rd[1]:
        raise _Corrupt("its BlackLevel does not match BlackLevelRepeatDim")
    pattern = bl[:rd[0] * rd[1]].reshape(rd)
    if quad_only and 2 % rd[0] == 0 and 2 % rd[1] == 0 and np.all(np.isfinite(pattern)):
        dh_n, dv_n = (len(tiff.get(ifd, t, []) or []) for t in (50715, 50716))
        if dh_n < w and dv_n < h:  # deltas too short are ignored below: the map repeats every 2x2 quad
            return None
    black = np.tile(pattern, (h // rd[0] + 1, w // rd[1] + 1))[:h, :w]
    dh = np.asarray(tiff.get(ifd, 50715, []), dtype=np.float64)
    dv = np.asarray(tiff.get(ifd, 50716, []), dtype=np.float64)
    if dh.size:
        black = black + dh[:w][None, :] if dh.size >= w else black
    if dv.size:
        black = black + dv[:h][:, None] if dv.size >= h else black
    return black


def read_raw(path: Union[str, Path]) -> RawPhoto:
    """Read a Bayer camera raw file (anything LibRaw reads) into a :class:`RawPhoto`.

    Raises :class:`UserError` (one line naming the file) for a missing, truncated or corrupt file, a format
    LibRaw cannot read, or a sensor that is not a 2x2 Bayer mosaic (X-Trans, Foveon, linear DNG).
    """
    import rawpy

    path = Path(path)
    size = _check_path(path)
    tiff = _open_tiff(path, size)
    notes: List[str] = []
    try:
        with rawpy.imread(str(path)) as raw:
            if raw.raw_type != rawpy.RawType.Flat:
                raise UserError(f"{path}: the sensor data is not a Bayer mosaic (Foveon, or a linear/demosaiced "
                                f"DNG); only Bayer raw files are supported yet")
            pattern = np.asarray(raw.raw_pattern)
            desc = raw.color_desc.decode("ascii", "replace")
            if pattern.shape != (2, 2) or raw.num_colors != 3 or desc not in ("RGBG", "RGB"):
                kind = "X-Trans (6x6)" if pattern.shape == (6, 6) else f"{desc} {pattern.shape[0]}x{pattern.shape[1]}"
                raise UserError(f"{path}: the sensor's colour filter is {kind}, not a 2x2 Bayer RGB mosaic; "
                                f"X-Trans and other non-Bayer sensors are not supported yet")
            visible = raw.raw_image_visible
            h, w = (visible.shape[0] // 2) * 2, (visible.shape[1] // 2) * 2
            if h < 2 or w < 2:
                raise UserError(f"{path}: the image is {visible.shape[1]}x{visible.shape[0]} pixels, smaller than "
                                f"one 2x2 colour quad")
            mosaic = np.array(visible[:h, :w], dtype=np.uint16)
            colors = np.asarray(raw.raw_colors_visible[:2, :2]).copy()
            blc = [float(v) for v in raw.black_level_per_channel]
            white = float(raw.white_level)
            cam_wb = [float(v) for v in raw.camera_whitebalance]
            day_wb = [float(v) for v in raw.daylight_whitebalance]
            rgb_xyz = np.asarray(raw.rgb_xyz_matrix, dtype=np.float64)[:3].copy()
            other = raw.other
    except UserError:
        raise
    except rawpy.LibRawError as exc:
        raise UserError(f"{path}: cannot read this raw file: {_libraw_reason(exc)}") from None
    except (OSError, MemoryError, ValueError) as exc:
        raise UserError(f"{path}: cannot read this raw file: {exc}") from None

    if (visible.shape[0], visible.shape[1]) != (h, w):
        notes.append(f"the odd last row/column of the {visible.shape[1]}x{visible.shape[0]} image was dropped "
                     f"so that it is whole 2x2 quads")
    cfa = np.where(colors == 3, 1, colors).astype(np.int8)  # LibRaw calls the second green 3
    if sorted(cfa.reshape(-1).tolist()) != [0, 1, 1, 2]:
        raise UserError(f"{path}: the colour filter pattern {colors.tolist()} is not an RGGB-type Bayer quad; "
                        f"not supported yet")
    cfa_pattern = "".join(_LETTERS[c] for c in cfa.reshape(-1))
    black = np.array([[blc[colors[i, j]] for j in range(2)] for i in range(2)], dtype=np.float32)
    if not white > black.max():
        raise UserError(f"{path}: white level {white:g} is not above the black level {black.max():g}; "
                        f"the file's metadata is corrupt")

    # DNG tags LibRaw does not give (or gives only in part): colour matrices, AsShotNeutral, NoiseProfile,
    # a per-pixel black.
    ifd0 = tiff.ifds[0] if tiff is not None and tiff.ifds else None
    rifd = tiff.raw_ifd() if tiff is not None else None
    is_dng = ifd0 is not None and 50706 in ifd0
    black_map = None
    noise_profile = None
    xyz_to_cam: Optional[np.ndarray] = None
    wb: Optional[np.ndarray] = None
    try:
        if is_dng:
            src = rifd if rifd is not None else ifd0
            bmap = _dng_black_map(tiff, src, h, w, quad_only=True)
            if bmap is not None:
                quad = np.tile(bmap[:2, :2], (h // 2, w // 2))
                if not np.allclose(bmap, quad):
                    black_map = bmap.astype(np.float32)
                    black = np.array([[bmap[i::2, j::2].mean() for j in range(2)] for i in range(2)],
                                     dtype=np.float32)
                    notes.append("the black level varies per pixel (DNG BlackLevelDeltaH/V or a repeat pattern "
                                 "larger than the CFA): subtracted pixel by pixel")
            neutral = tiff.get(ifd0, 50728)
            if neutral and len(neutral) >= 3 and min(neutral[:3]) > 0:
                wb = 1.0 / np.asarray(neutral[:3], dtype=np.float64)
            cms = {}
            for cm_tag, ill_tag in ((50721, 50778), (50722, 50779)):
                vals = tiff.get(ifd0, cm_tag)
                if vals and len(vals) >= 9 and np.all(np.isfinite(vals[:9])):
                    cms[cm_tag] = (np.asarray(vals[:9], dtype=np.float64).reshape(3, 3),
                                   (tiff.get(ifd0, ill_tag) or [0])[0])
            # the matrix stated for D65 (what sRGB's white is) when there is one, else ColorMatrix1
            d65 = [m for m, ill in cms.values() if ill == _D65]
            if d65:
                xyz_to_cam = d65[0]
            elif cms:
                xyz_to_cam = cms[min(cms)][0]
            for ifd in (rifd, ifd0):
                if ifd is not None and 51041 in ifd:
                    prof = np.asarray(tiff.get(ifd, 51041), dtype=np.float64)
                    if prof.size == 2:
                        noise_profile = np.tile(prof.reshape(1, 2), (3, 1))
                    elif prof.size == 6:
                        noise_profile = prof.reshape(3, 2)
                    else:
                        notes.append(f"NoiseProfile with {prof.size} numbers (not 2 or 6) ignored")
                    if noise_profile is not None and (not np.all(np.isfinite(noise_profile))
                                                      or np.any(noise_profile[:, 0] < 0)):
                        notes.append(f"NoiseProfile {prof.tolist()} is not valid (negative or not finite): "
                                     f"ignored")
                        noise_profile = None
                    break
    except (_Corrupt, struct.error) as exc:
        raise UserError(f"{path}: DNG metadata unreadable: {exc}") from None

    if wb is None:
        if cam_wb[1] > 0 and min(cam_wb[:3]) > 0:
            wb = np.asarray(cam_wb[:3], dtype=np.float64)
        elif day_wb[1] > 0 and min(day_wb[:3]) > 0:
            wb = np.asarray(day_wb[:3], dtype=np.float64)
            notes.append("no white balance as shot in the file: the camera's daylight balance is used")
        else:
            wb = np.ones(3)
            notes.append("no white balance in the file: none applied (gains 1, 1, 1)")
    wb = (wb / wb[1]).astype(np.float32)

    if xyz_to_cam is None and np.any(rgb_xyz):
        xyz_to_cam = rgb_xyz
    cam_to_srgb = np.eye(3)
    if xyz_to_cam is None:
        notes.append("no colour matrix known for this camera: camera RGB is taken as linear sRGB")
    else:
        try:
            cam_to_srgb = _cam_to_srgb(xyz_to_cam)
        except np.linalg.LinAlgError:
            notes.append("the colour matrix is singular: camera RGB is taken as linear sRGB")

    tags = _read_exif(path)
    t, iso, fn = _exposure_from(tags, other, notes)
    missing = [n for n, v in (("exposure time", t), ("ISO", iso), ("f-number", fn)) if v is None]
    if missing:
        notes.append(f"no {', '.join(missing)} in the metadata: the view's exposure is assumed equal to the "
                     f"scene's median (exposure scale 1)")
    make = str(tags.get("Image Make", "")).strip()
    model = str(tags.get("Image Model", "")).strip()
    return RawPhoto(path=path, mosaic=mosaic, cfa=cfa, cfa_pattern=cfa_pattern, black_level=black,
                    white_level=white, white_balance=wb, cam_to_srgb=cam_to_srgb.astype(np.float64),
                    xyz_to_cam=xyz_to_cam, black_map=black_map, exposure_time=t, iso=iso, f_number=fn,
                    noise_profile=noise_profile, make=make, model=model, notes=notes)


# ----------------------------------------------------------------------------------------------------------
# linear values, exposure, preview

def normalised_mosaic(photo: RawPhoto) -> np.ndarray:
    """float32 [H, W]: (raw - black) / (white - black) per sample, NOT clipped (negative values are noise)."""
    h, w = photo.shape
    black = photo.black_map if photo.black_map is not None else np.tile(photo.black_level, (h // 2, w // 2))
    return (photo.mosaic.astype(np.float32) - black) / (np.float32(photo.white_level) - black)


def _planes(photo: RawPhoto, x: np.ndarray) -> Dict[int, List[np.ndarray]]:
    """The CFA planes of ``x`` ([H/2, W/2] each), grouped by colour 0, 1, 2."""
    out: Dict[int, List[np.ndarray]] = {0: [], 1: [], 2: []}
    for i in range(2):
        for j in range(2):
            out[int(photo.cfa[i, j])].append(x[i::2, j::2])
    return out


def linear_rgb(photo: RawPhoto, white_balance: bool = True) -> np.ndarray:
    """float32 [H/2, W/2, 3] linear camera RGB: black-subtracted, divided by (white - black), not clipped at zero
    (the noise around black stays zero-mean), each 2x2 CFA quad binned to one pixel (R, mean of the two G, B; no
    interpolation), times the camera white balance when ``white_balance``."""
    planes = _planes(photo, normalised_mosaic(photo))
    rgb = np.stack([planes[0][0], (planes[1][0] + planes[1][1]) * np.float32(0.5), planes[2][0]], axis=-1)
    if white_balance:
        rgb = rgb * photo.white_balance.astype(np.float32)
    return rgb.astype(np.float32, copy=False)


def exposure_scale(photos: Sequence[RawPhoto], notes: Optional[List[str]] = None) -> List[float]:
    """Each photo's exposure (time x ISO / f-number^2) relative to the median over ``photos``.

    A factor missing from every photo cancels and is left out (e.g. a phone that never writes its fixed
    aperture). A photo missing a factor that others have gets 1.0: its exposure is assumed to be the scene's
    median; a line saying so is appended to ``notes`` when given.
    """
    fields = ("exposure_time", "iso", "f_number")
    present = {f: [getattr(p, f) is not None for p in photos] for f in fields}
    used = [f for f in fields if any(present[f])]
    values: List[Optional[float]] = []
    for k, p in enumerate(photos):
        if not used or not all(present[f][k] for f in used):
            values.append(None)
            if notes is not None:
                lack = [f for f in fields if getattr(p, f) is None]
                notes.append(f"{p.path}: no {', '.join(lack).replace('_', ' ')} in the metadata: exposure assumed "
                             f"equal to the scene's median (scale 1.0)")
            continue
        t = p.exposure_time if "exposure_time" in used else 1.0
        iso = p.iso if "iso" in used else 1.0
        fn = p.f_number if "f_number" in used else 1.0
        values.append(t * iso / fn ** 2)
    known = [v for v in values if v is not None]
    if not known:
        return [1.0] * len(photos)
    median = float(np.median(known))
    return [1.0 if v is None else float(v / median) for v in values]


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer curve (:func:`retinexgs.data.srgb.linear_to_srgb`, clipped to [0, 1]) as float32."""
    return np.asarray(linear_to_srgb(x), dtype=np.float32)


def preview_srgb(photo: RawPhoto, percentile: float = 99.0, target: float = 0.9,
                 full_size: bool = False) -> np.ndarray:
    """uint8 [H/2, W/2, 3] (``full_size``: [H, W, 3]): a viewable preview for pose estimation (structure from
    motion).

    linear_rgb with the camera white balance (``full_size``: the bilinear demosaic of :func:`linear_srgb`
    instead of the 2x2 binning, so that the preview has the size the scene's views and cameras have), camera ->
    linear sRGB, scaled so that the ``percentile`` of the luminance maps to ``target`` (a night photo comes out
    bright), sRGB curve, then a light bilateral filter (edges kept, night noise smoothed; twice the reach at full
    size, where a pixel is half as wide). The filter runs after the curve because its colour threshold is then
    about equally visible in shadows and highlights.
    """
    import cv2

    if full_size:
        rgb = _demosaiced_srgb_linear(photo)
    else:
        rgb = linear_rgb(photo, white_balance=True) @ photo.cam_to_srgb.T.astype(np.float32)
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    level = float(np.percentile(lum, percentile))
    scale = target / level if level > 1e-6 else 1.0
    srgb = srgb_encode(rgb * np.float32(scale))
    d, space = (9, 3.0) if full_size else (5, 1.5)
    srgb = cv2.bilateralFilter(np.ascontiguousarray(srgb), d=d, sigmaColor=0.08, sigmaSpace=space)
    return np.clip(np.round(srgb * 255.0), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------------------
# full-size views for scenes (stage 3a): demosaic, the view's sRGB image, size and exposure without the mosaic

CFA_CHANNEL = {"R": 0, "G": 1, "B": 2}  # a CFA letter -> its RGB channel
_K_RB = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], dtype=np.float64) / 4.0
_K_G = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]], dtype=np.float64) / 4.0


def _correlate3(x: np.ndarray, k: np.ndarray) -> np.ndarray:
    """3x3 correlation of [H, W] with zeros outside (the normalisation by the mask's own response handles edges)."""
    p = np.pad(x, 1)
    h, w = x.shape
    out = np.zeros_like(x)
    for i in range(3):
        for j in range(3):
            if k[i, j]:
                out += x.dtype.type(k[i, j]) * p[i:i + h, j:j + w]
    return out


def demosaic_bilinear_reference(x: np.ndarray, cfa: Union[str, np.ndarray]) -> np.ndarray:
    """The definition :func:`demosaic_bilinear` equals bit for bit (tests, the darken bench's reference pipeline):
    [H, W, 3] from a mosaic [H, W] (float32 stays float32, anything else becomes float64): each missing
    sample is the mean of its nearest samples of that colour (bilinear; exact for a linear ramp away from the
    border). At the border, only samples inside count. ``cfa``: "RGGB"-style letters read from the top-left
    pixel, or the [2, 2] channel indices of :attr:`RawPhoto.cfa`."""
    x = np.asarray(x)
    x = x if x.dtype == np.float32 else x.astype(np.float64)
    quad = (np.array([CFA_CHANNEL[c] for c in cfa.upper()]).reshape(2, 2) if isinstance(cfa, str)
            else np.asarray(cfa).reshape(2, 2))
    h, w = x.shape
    idx = np.tile(quad, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    out = np.empty((h, w, 3), dtype=x.dtype)
    for c, k in ((0, _K_RB), (1, _K_G), (2, _K_RB)):
        m = (idx == c).astype(x.dtype)
        out[..., c] = _correlate3(x * m, k) / _correlate3(m, k)
    return out


def demosaic_bilinear(x: np.ndarray, cfa: Union[str, np.ndarray]) -> np.ndarray:
    """[H, W, 3] from a mosaic [H, W] (float32 stays float32, anything else becomes float64), bilinear: each
    missing sample is the mean of its nearest samples of that colour; at the border only samples inside count.
    ``cfa``: "RGGB"-style letters read from the top-left pixel, or the [2, 2] channel indices of
    :attr:`RawPhoto.cfa`. :func:`demosaic_bilinear_reference` bit for bit, in about a sixth of its passes.

    The reference correlates each channel's masked mosaic with a 3x3 kernel over the whole image, most terms
    zero. Here each of the four CFA phases is a strided slice, and only the terms that fall on the channel's own
    samples are summed, in the same (raster) order and with the same weights (powers of two: exact), so every
    sum rounds as there; the zeros left out change no sum. The normalisation (the kernel weights of the samples
    inside the image) is 1 away from the border, and dividing by 1 is exact, so only each phase's first and last
    row and column are divided."""
    x = np.asarray(x)
    x = x if x.dtype == np.float32 else x.astype(np.float64)
    quad = (np.array([CFA_CHANNEL[c] for c in cfa.upper()]).reshape(2, 2) if isinstance(cfa, str)
            else np.asarray(cfa).reshape(2, 2))
    h, w = x.shape
    p = np.pad(x, 1)
    out = np.empty((h, w, 3), dtype=x.dtype)
    for c, k in ((0, _K_RB), (1, _K_G), (2, _K_RB)):
        for py in (0, 1):
            for px in (0, 1):
                nr, nc = (h - py + 1) // 2, (w - px + 1) // 2
                if nr <= 0 or nc <= 0:
                    continue
                terms = [(i, j, x.dtype.type(k[i, j])) for i in range(3) for j in range(3)
                         if k[i, j] and quad[(py + i + 1) % 2, (px + j + 1) % 2] == c]
                num = None
                for i, j, wgt in terms:
                    term = wgt * p[py + i:py + i + 2 * nr - 1:2, px + j:px + j + 2 * nc - 1:2]
                    num = term if num is None else np.add(num, term, out=num)
                rows = np.arange(py, h, 2) - 1  # the top row / left column of each sample's 3x3 window
                cols = np.arange(px, w, 2) - 1
                edges = []  # from the undivided sums: a corner is in two edges, divided once
                for r, q, sel in ((rows[:1, None], cols[None], np.s_[:1, :]),
                                  (rows[-1:, None], cols[None], np.s_[-1:, :]),
                                  (rows[:, None], cols[None, :1], np.s_[:, :1]),
                                  (rows[:, None], cols[None, -1:], np.s_[:, -1:])):
                    den = np.zeros(np.broadcast_shapes(r.shape, q.shape), dtype=x.dtype)
                    for i, j, wgt in terms:  # sums of powers of two: exact in any order
                        den += wgt * (((r + i >= 0) & (r + i < h)) & ((q + j >= 0) & (q + j < w)))
                    edges.append((sel, num[sel] / den))
                for sel, value in edges:
                    num[sel] = value
                out[py::2, px::2, c] = num
    return out


def _demosaiced_srgb_linear(photo: RawPhoto) -> np.ndarray:
    """float32 [H, W, 3] linear sRGB at full size: normalised (not clipped), bilinear demosaic, camera white
    balance, camera -> sRGB matrix."""
    rgb = demosaic_bilinear(normalised_mosaic(photo), photo.cfa)
    rgb *= photo.white_balance.astype(np.float32)
    return (rgb @ photo.cam_to_srgb.T.astype(np.float32)).astype(np.float32, copy=False)


def view_srgb(photo: RawPhoto, exposure_factor: float = 1.0, clip: bool = True) -> np.ndarray:
    """float32 [H, W, 3] in [0, 1]: the photo as a scene view reads it (stage 3a): linear sRGB at full size
    (:func:`_demosaiced_srgb_linear`), divided by ``exposure_factor`` (the view's exposure relative to the
    scene's reference, :func:`folder_exposure`), clipped to [0, 1], sRGB-encoded; full float precision.
    ``clip=False`` (training's target in linear light, stage 3b): not clipped, encoded by
    :func:`retinexgs.data.srgb.linear_to_srgb_extended` (negative noise around black and light past white kept)."""
    from retinexgs.data.srgb import linear_to_srgb, linear_to_srgb_extended

    rgb = view_linear(photo, exposure_factor)
    encoded = linear_to_srgb(rgb) if clip else linear_to_srgb_extended(rgb)
    return encoded.astype(np.float32, copy=False)


def view_linear(photo: RawPhoto, exposure_factor: float = 1.0) -> np.ndarray:
    """float32 [H, W, 3]: the linear light :func:`view_srgb` encodes (:func:`_demosaiced_srgb_linear` divided by
    ``exposure_factor``), for a reader that encodes only part of it (the encoding is per value: the same bits)."""
    if not (np.isfinite(exposure_factor) and exposure_factor > 0):
        raise ValueError(f"exposure factor must be positive, got {exposure_factor}")
    rgb = _demosaiced_srgb_linear(photo)
    if exposure_factor != 1.0:
        rgb /= np.float32(exposure_factor)
    return rgb


@dataclass
class RawHeader:
    """What a scene needs of a raw file without its mosaic: the size :func:`read_raw` gives (visible area,
    whole 2x2 quads), camera make/model (EXIF; "" when not stated) and the exposure metadata (None when
    missing)."""
    path: Path
    width: int
    height: int
    make: str = ""
    model: str = ""
    exposure_time: Optional[float] = None
    iso: Optional[float] = None
    f_number: Optional[float] = None

    @property
    def camera(self) -> str:
        """"make model" as stated, or "" when the file names no camera."""
        return " ".join(v for v in (self.make, self.model) if v).strip()


def read_header(path: Union[str, Path]) -> RawHeader:
    """The :class:`RawHeader` of a raw file: the same checks as :func:`read_raw` before LibRaw (missing, tiny,
    truncated TIFF structure), then LibRaw's sizes and metadata without decoding the mosaic. UserError (one line
    naming the file) for anything LibRaw refuses."""
    import rawpy

    path = Path(path)
    size = _check_path(path)
    _open_tiff(path, size)
    raw = rawpy.RawPy()
    try:
        raw.open_file(str(path))
        w, h = int(raw.sizes.width), int(raw.sizes.height)
        other = raw.other
        t_other = (float(other.shutter_speed), float(other.aperture), float(other.iso_speed))
    except rawpy.LibRawError as exc:
        raise UserError(f"{path}: cannot read this raw file: {_libraw_reason(exc)}") from None
    except (OSError, MemoryError, ValueError) as exc:
        raise UserError(f"{path}: cannot read this raw file: {exc}") from None
    finally:
        raw.close()
    if h < 2 or w < 2:
        raise UserError(f"{path}: the image is {w}x{h} pixels, smaller than one 2x2 colour quad")

    class _Other:  # LibRaw's values, read while the file was open
        shutter_speed, aperture, iso_speed = t_other

    tags = _read_exif(path)
    t, iso, fn = _exposure_from(tags, _Other, [])
    return RawHeader(path, (w // 2) * 2, (h // 2) * 2, str(tags.get("Image Make", "")).strip(),
                     str(tags.get("Image Model", "")).strip(), t, iso, fn)


def is_raw_path(path: Union[str, Path]) -> bool:
    """True when the name ends in one of :data:`BAYER_RAW_EXTENSIONS` or is a GoPro .gpr (any case): a .gpr a scene
    names goes to the raw reader, which refuses it in one line (:data:`GPR_ADVICE`), not to Pillow."""
    return Path(path).suffix.lower() in BAYER_RAW_EXTENSIONS + GPR_EXTENSIONS


@dataclass
class FolderExposure:
    """The exposures of a folder's raw files: ``factors[name]`` = the file's exposure (time x ISO / f-number^2)
    relative to the folder's reference, the median over its raw files (:func:`exposure_scale`); 1.0 for a file
    without the metadata, listed in ``missing``. ``headers[name]``: each file's :class:`RawHeader`."""
    folder: Path
    factors: Dict[str, float]
    missing: List[str]
    headers: Dict[str, RawHeader]


_FOLDER_EXPOSURES: Dict[tuple, FolderExposure] = {}
_FOLDER_LOCK = threading.Lock()


def _folder_key(folder: Path) -> tuple:
    """What changes when a raw file of ``folder`` is added, removed or replaced (name, size, mtime, ctime)."""
    entries = []
    for p in sorted(folder.iterdir(), key=lambda q: q.name):
        if is_raw_path(p) and not p.name.startswith(".") and p.is_file():
            st = p.stat()
            entries.append((p.name, st.st_size, st.st_mtime_ns, st.st_ctime_ns))
    return (str(folder.resolve()), tuple(entries))


def folder_exposure(folder: Union[str, Path]) -> FolderExposure:
    """:class:`FolderExposure` of the raw files directly inside ``folder``, from their headers only (EXIF /
    LibRaw metadata, no mosaic), computed once per process while the folder's raw files are unchanged (a
    thread-safe cache: the loader reads views from several threads)."""
    folder = Path(folder)
    key = _folder_key(folder)
    with _FOLDER_LOCK:
        hit = _FOLDER_EXPOSURES.get(key)
        if hit is not None:
            return hit
        headers = [read_header(folder / name) for name, *_ in key[1]]
        factors = exposure_scale(headers)  # type: ignore[arg-type]  # RawHeader has the exposure fields
        fields = ("exposure_time", "iso", "f_number")
        used = [f for f in fields if any(getattr(h, f) is not None for h in headers)]  # as exposure_scale
        missing = [h.path.name for h in headers if not used or any(getattr(h, f) is None for f in used)]
        result = FolderExposure(folder, {h.path.name: f for h, f in zip(headers, factors)}, missing,
                                {h.path.name: h for h in headers})
        _FOLDER_EXPOSURES[key] = result
        return result


def read_view_srgb(path: Union[str, Path], clip: bool = True) -> np.ndarray:
    """float32 [H, W, 3] in [0, 1]: a raw file as a scene view (:func:`view_srgb`, ``clip`` as there), divided by
    its exposure relative to the median of its folder's raw files (:func:`folder_exposure`). UserError naming the
    file for anything that cannot be read."""
    path = Path(path)
    photo = read_raw(path)  # first: a missing or broken file gets read_raw's line naming it
    factor = folder_exposure(path.parent).factors.get(path.name, 1.0)
    return view_srgb(photo, factor, clip)


def read_view_linear(path: Union[str, Path]) -> np.ndarray:
    """float32 [H, W, 3]: the linear light :func:`read_view_srgb` encodes (:func:`view_linear` at the file's
    exposure factor in its folder). UserError naming the file for anything that cannot be read."""
    path = Path(path)
    photo = read_raw(path)
    factor = folder_exposure(path.parent).factors.get(path.name, 1.0)
    return view_linear(photo, factor)


# ----------------------------------------------------------------------------------------------------------
# noise

def noise_from_profile(photo: RawPhoto) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(a, b), float64 [3] each (R, G, B): the variance of one mosaic sample of that colour at normalised signal
    x is a*x + b, in the units of :func:`normalised_mosaic` (= :func:`linear_rgb` before binning and white
    balance). From the DNG NoiseProfile; None when the file has none.

    The DNG's unit is (raw - black) / (white - black) with the file's own BlackLevel and WhiteLevel, which are
    the levels used here, so S and O carry over unchanged. :func:`noise_in_linear_rgb` converts to the units of
    the binned, white-balanced image.
    """
    if photo.noise_profile is None:
        return None
    return photo.noise_profile[:, 0].copy(), photo.noise_profile[:, 1].copy()


def noise_in_linear_rgb(a: np.ndarray, b: np.ndarray, photo: RawPhoto,
                        white_balance: bool = True) -> Tuple[np.ndarray, np.ndarray]:
    """The per-sample model (a, b) converted to the pixels of ``linear_rgb(photo, white_balance)``: G is the mean
    of two samples (variance halved); a gain g (white balance) maps y = g*x, so var(y) = g*a*y + g^2*b."""
    n = np.array([1.0, 2.0, 1.0])
    g = photo.white_balance.astype(np.float64) if white_balance else np.ones(3)
    return g * np.asarray(a) / n, g ** 2 * np.asarray(b) / n


def estimate_noise(photo: RawPhoto, block: int = 16, min_blocks: int = 3) -> Tuple[np.ndarray, np.ndarray]:
    """(a, b), float64 [3] (R, G, B), estimated from the pixels, in the units of :func:`noise_from_profile`.

    Method: each CFA plane is cut into ``block`` x ``block`` blocks. In a block, the variance of the noise is
    half the variance of the differences between horizontal neighbours (a constant or a linear ramp of the
    scene drops out). A block is taken as flat when the same measure at a distance of two pixels is not more
    than 1.5x the one at one pixel (texture grows with distance, white noise does not), and it has no
    saturated sample. Flat blocks of a colour are sorted by mean into up to 16 equal-count bins; each bin gives
    (median mean, median variance); var = a*x + b is fitted by least squares weighted by 1/var^2 (relative
    error). A colour with too few flat blocks gets NaN.
    """
    x = normalised_mosaic(photo).astype(np.float64)
    sat = photo.mosaic >= 0.98 * photo.white_level
    a_out, b_out = np.full(3, np.nan), np.full(3, np.nan)
    planes, sats = _planes(photo, x), _planes(photo, sat)
    for c in range(3):
        means, vars_ = [], []
        for p, s in zip(planes[c], sats[c]):
            hb, wb = p.shape[0] // block, p.shape[1] // block
            if hb == 0 or wb == 0:
                continue
            blk = p[:hb * block, :wb * block].reshape(hb, block, wb, block).transpose(0, 2, 1, 3)
            sblk = s[:hb * block, :wb * block].reshape(hb, block, wb, block).transpose(0, 2, 1, 3)
            d1 = np.diff(blk, axis=-1)
            d2 = blk[..., 2:] - blk[..., :-2]
            v1 = d1.reshape(hb, wb, -1).var(axis=-1) / 2
            v2 = d2.reshape(hb, wb, -1).var(axis=-1) / 2
            keep = (~sblk.reshape(hb, wb, -1).any(axis=-1)) & (v1 > 0) & (v2 <= 1.5 * v1)
            means.append(blk.reshape(hb, wb, -1).mean(axis=-1)[keep])
            vars_.append(v1[keep])
        if not means:
            continue
        m, v = np.concatenate(means), np.concatenate(vars_)
        if m.size < min_blocks:
            continue
        order = np.argsort(m)
        bins = np.array_split(order, min(16, m.size // max(1, min_blocks)) or 1)
        bm = np.array([np.median(m[i]) for i in bins if i.size])
        bv = np.array([np.median(v[i]) for i in bins if i.size])
        if bm.size < 2 or np.ptp(bm) <= 0:  # one level: no slope to fit; all of it is offset
            b_out[c], a_out[c] = float(np.median(v)), 0.0
            continue
        design = np.stack([bm / bv, 1.0 / bv], axis=1)
        (a_fit, b_fit), *_ = np.linalg.lstsq(design, np.ones_like(bv), rcond=None)
        a_out[c], b_out[c] = a_fit, b_fit
    return a_out, b_out
