"""Writing a minimal DNG: one uncompressed strip of a Bayer mosaic, with the tags a raw reader needs.

Used for test fixtures now and for ``darken --raw`` later. The file is a little-endian TIFF written by hand
(it is small): IFD0 holds the raw image itself (NewSubfileType 0, PhotometricInterpretation CFA) and the DNG
tags; an EXIF sub-IFD holds the exposure. Why not a library: a trial with pidng found that LibRaw reads its
single tile with the wrong row stride when the width is not a multiple of the tile size, and that its EXIF
sub-IFD writer fails; an uncompressed strip avoids both.

Written tags: BlackLevelRepeatDim 2x2 + BlackLevel (one value per CFA position), WhiteLevel, CFARepeatPatternDim,
CFAPattern, CFAPlaneColor, CFALayout, AsShotNeutral, ColorMatrix1 with CalibrationIlluminant1 = D65,
NoiseProfile (when given) and EXIF ExposureTime, FNumber, ISOSpeedRatings (when given). The file goes through
:func:`retinexgs.fileio.atomic_write`.
"""
from __future__ import annotations

import struct
from fractions import Fraction
from pathlib import Path
from typing import List, Optional, Sequence, Tuple, Union

import numpy as np

from retinexgs.fileio import atomic_write

# TIFF field types used here
_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _UNDEFINED, _SRATIONAL, _DOUBLE = 1, 2, 3, 4, 5, 7, 10, 12
_COLOURS = {"R": 0, "G": 1, "B": 2}
_D65 = 21
MIN_SIDE = 22  # pixels: LibRaw 0.22 rejects a DNG narrower or shorter than this  # EXIF LightSource code of D65, the illuminant ColorMatrix1 is stated for

Entry = Tuple[int, int, list]


def _rational(value: float, signed: bool) -> Tuple[int, int]:
    """``value`` as a TIFF (S)RATIONAL numerator/denominator pair that fits 32 bits."""
    limit = 2**31 - 1 if signed else 2**32 - 1
    frac = Fraction(float(value)).limit_denominator(1_000_000)
    while abs(frac.numerator) > limit or frac.denominator > limit:  # a huge value: give up precision, not range
        frac = Fraction(float(value)).limit_denominator(max(1, frac.denominator // 10))
    if not signed and frac < 0:
        raise ValueError(f"a negative value {value} cannot be written as an unsigned TIFF RATIONAL")
    return frac.numerator, frac.denominator


def _pack(ftype: int, values: list) -> bytes:
    """The little-endian bytes of one field's values."""
    if ftype in (_BYTE, _UNDEFINED):
        return bytes(int(v) for v in values)
    if ftype == _ASCII:
        return "".join(values).encode("ascii") + b"\0"
    if ftype == _SHORT:
        return struct.pack(f"<{len(values)}H", *[int(v) for v in values])
    if ftype == _LONG:
        return struct.pack(f"<{len(values)}I", *[int(v) for v in values])
    if ftype in (_RATIONAL, _SRATIONAL):
        pairs = [_rational(v, ftype == _SRATIONAL) for v in values]
        return struct.pack(f"<{2 * len(pairs)}{'i' if ftype == _SRATIONAL else 'I'}",
                           *[x for p in pairs for x in p])
    if ftype == _DOUBLE:
        return struct.pack(f"<{len(values)}d", *[float(v) for v in values])
    raise ValueError(f"TIFF field type {ftype} is not written here")


def _count(ftype: int, values: list) -> int:
    return len("".join(values)) + 1 if ftype == _ASCII else len(values)


def _ifd(entries: List[Entry], start: int) -> bytes:
    """One IFD placed at file offset ``start``, its out-of-line values right after it; next-IFD offset 0.
    The size does not depend on the values of LONG offsets, so callers lay out the file with placeholders."""
    entries = sorted(entries, key=lambda e: e[0])  # TIFF requires ascending tags
    head = struct.pack("<H", len(entries))
    data = b""
    data_start = start + 2 + 12 * len(entries) + 4
    for tag, ftype, values in entries:
        raw = _pack(ftype, values)
        if len(raw) <= 4:
            head += struct.pack("<HHI", tag, ftype, _count(ftype, values)) + raw.ljust(4, b"\0")
        else:
            if len(data) % 2:
                data += b"\0"  # values start on a word boundary
            head += struct.pack("<HHII", tag, ftype, _count(ftype, values), data_start + len(data))
            data += raw
    out = head + struct.pack("<I", 0) + data
    return out + (b"\0" if len(out) % 2 else b"")


def _black_values(black_level: Union[float, Sequence[float]]) -> List[float]:
    vals = [float(black_level)] * 4 if np.isscalar(black_level) else [float(v) for v in black_level]
    if len(vals) != 4:
        raise ValueError(f"black_level: one number or four (one per 2x2 CFA position, row-major), got {len(vals)}")
    return vals


def write_dng(path: Union[str, Path], mosaic_uint16: np.ndarray, cfa: str = "RGGB",
              black_level: Union[float, Sequence[float]] = 0, white_level: int = 65535,
              as_shot_neutral: Sequence[float] = (1.0, 1.0, 1.0),
              color_matrix1: Optional[np.ndarray] = None,
              noise_profile: Optional[Sequence[float]] = None, exposure_time: Optional[float] = None,
              iso: Optional[float] = None, f_number: Optional[float] = None,
              make: str = "RetinexGS", model: str = "Simulated camera") -> Path:
    """Write ``mosaic_uint16`` ([H, W] uint16 Bayer mosaic) as a DNG at ``path`` (atomically).

    ``cfa``: the 2x2 pattern read row-major from the top-left pixel ("RGGB", "BGGR", "GRBG", "GBRG").
    ``black_level``: one value, or four in CFA-position order (row-major over the 2x2 quad).
    ``as_shot_neutral``: the camera-RGB of a neutral (the white balance is its inverse).
    ``color_matrix1``: XYZ -> camera RGB, 3x3, stated for D65; identity when None.
    ``noise_profile``: DNG NoiseProfile, (S, O) once or per colour plane R, G, B (2 or 6 numbers), in the
    normalised units (raw - black) / (white - black). Exposure fields are written to EXIF when given.
    Returns ``path``.
    """
    mosaic = np.asarray(mosaic_uint16)
    if mosaic.ndim != 2 or mosaic.dtype != np.uint16:
        raise ValueError(f"mosaic must be a 2-D uint16 array, got {mosaic.dtype} {mosaic.shape}")
    h, w = mosaic.shape
    if h < MIN_SIDE or w < MIN_SIDE:  # LibRaw refuses smaller images as "unsupported"
        raise ValueError(f"mosaic of {w}x{h} pixels: LibRaw reads only images of at least {MIN_SIDE}x{MIN_SIDE}")
    cfa = cfa.upper()
    if len(cfa) != 4 or sorted(cfa) != ["B", "G", "G", "R"]:
        raise ValueError(f"cfa {cfa!r}: four letters, one R, two G, one B (e.g. 'RGGB')")
    blacks = _black_values(black_level)
    if not 0 < white_level <= 65535 or any(b >= white_level or b < 0 for b in blacks):
        raise ValueError(f"need 0 <= black_level < white_level <= 65535 (got {blacks}, {white_level})")
    neutral = [float(v) for v in as_shot_neutral]
    if len(neutral) != 3 or min(neutral) <= 0:
        raise ValueError(f"as_shot_neutral: three positive numbers, got {as_shot_neutral}")
    cm = np.eye(3) if color_matrix1 is None else np.asarray(color_matrix1, dtype=np.float64)
    if cm.shape != (3, 3):
        raise ValueError(f"color_matrix1 must be 3x3, got {cm.shape}")

    blacks_int = all(float(b).is_integer() for b in blacks)
    ifd0: List[Entry] = [
        (254, _LONG, [0]), (256, _LONG, [w]), (257, _LONG, [h]), (258, _SHORT, [16]), (259, _SHORT, [1]),
        (262, _SHORT, [32803]), (271, _ASCII, [make]), (272, _ASCII, [model]), (273, _LONG, [0]),
        (274, _SHORT, [1]), (277, _SHORT, [1]), (278, _LONG, [h]), (279, _LONG, [h * w * 2]),
        (284, _SHORT, [1]), (305, _ASCII, ["RetinexGS"]),
        (33421, _SHORT, [2, 2]), (33422, _BYTE, [_COLOURS[c] for c in cfa]),
        (37398, _BYTE, [1, 0, 0, 0]),
        (50706, _BYTE, [1, 4, 0, 0]), (50707, _BYTE, [1, 1, 0, 0]), (50708, _ASCII, [f"{make} {model}"]),
        (50710, _BYTE, [0, 1, 2]), (50711, _SHORT, [1]),
        (50713, _SHORT, [2, 2]), (50714, _LONG if blacks_int else _RATIONAL, blacks),
        (50717, _LONG, [int(white_level)]),
        (50721, _SRATIONAL, cm.reshape(-1).tolist()), (50728, _RATIONAL, neutral),
        (50778, _SHORT, [_D65]),
    ]
    if noise_profile is not None:
        npf = [float(v) for v in noise_profile]
        if len(npf) not in (2, 6):
            raise ValueError(f"noise_profile: 2 or 6 numbers (S, O per plane), got {len(npf)}")
        ifd0.append((51041, _DOUBLE, npf))
    exif: List[Entry] = [(36864, _UNDEFINED, list(b"0230"))]
    if exposure_time is not None:
        exif.append((33434, _RATIONAL, [exposure_time]))
    if f_number is not None:
        exif.append((33437, _RATIONAL, [f_number]))
    if iso is not None:
        exif.append((34855, _SHORT, [min(65535, int(round(iso)))]))
    ifd0.append((34665, _LONG, [0]))

    # Lay out: header | IFD0 + values | EXIF IFD + values | strip. Sizes first, offsets second.
    ifd0_len = len(_ifd(ifd0, 8))
    exif_at = 8 + ifd0_len
    exif_bytes = _ifd(exif, exif_at)
    strip_at = exif_at + len(exif_bytes)
    strip_at += (-strip_at) % 16  # aligned strip: cheap, and some readers like it
    ifd0 = [(t, f, [strip_at] if t == 273 else [exif_at] if t == 34665 else v) for t, f, v in ifd0]
    ifd0_bytes = _ifd(ifd0, 8)
    head = b"II*\0" + struct.pack("<I", 8) + ifd0_bytes + exif_bytes
    head += b"\0" * (strip_at - len(head))
    pixels = mosaic.astype("<u2", copy=False).tobytes()

    def write(f) -> None:
        f.write(head)
        f.write(pixels)

    return atomic_write(path, write)
