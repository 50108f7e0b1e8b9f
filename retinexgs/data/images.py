"""Image files: listing, reading (with clear errors), atomic writing and resizing.

Images are read with Pillow and scaled to [0,1] by their bit depth: 8- and 16-bit grey, grey+alpha, RGB
and RGBA (alpha is dropped, grey is repeated over the three channels; 16-bit RGB(A), which Pillow
reduces to 8 bits, is decoded by OpenCV at full depth when it is installed).

Readable types: :data:`IMAGE_EXTENSIONS` (any case), the one list every reader and "no photos" message uses.
HEIC/HEIF (a phone's default) is read through pillow-heif, registered with Pillow on the first image opened.

Camera raw files (:data:`RAW_EXTENSIONS`, those whose cameras LibRaw reads as a 2x2 Bayer mosaic; issue #52
stage 3a, docs/raw.md "Raw scenes") are photos too: :func:`read_image_float` reads one through
:func:`retinexgs.data.camera_raw.read_view_srgb`: black-subtracted, bilinear-demosaiced at full size (the sensor's
visible area, so poses and intrinsics declared for it fit), the camera's as-shot white balance and camera -> sRGB
matrix, divided by its exposure relative to the median of its folder's raw files, clipped to [0, 1] and
sRGB-encoded, as float32 (no 8-bit rounding; :func:`read_image` rounds to 8 bits as for a 16-bit PNG).
:func:`image_size` of a raw file reads LibRaw's sizes, not the mosaic. ``unclipped=True`` (training in linear light,
stage 3b) keeps the view's values beyond [0, 1] (negative noise around black, light past white) in the extended
encoding (:func:`retinexgs.data.srgb.linear_to_srgb_extended`); other photos ignore it (their values are in [0, 1]).

The undistort/downscale cache keeps a raw view's processed copy as a ``.npy`` file (:data:`FLOAT_CACHE_EXTENSION`,
float32 [H,W,3], extended-encoded; :mod:`retinexgs.data.undistort`): :func:`read_image_float` reads it, clipped to
[0, 1] unless ``unclipped``. It is a cache format, not a photo type (not in :data:`IMAGE_EXTENSIONS`).

Orientation: the EXIF orientation tag is ignored for every format, as COLMAP ignores it, so poses and pixels
stay consistent: a photo is read as its pixels are stored. For JPEG that is Pillow's default. For HEIC the
decoder (libheif) always turns the image upright by the container's rotation and reports the orientation it
applied (``info["original_orientation"]``); that turn is undone here, so a HEIC reads like the JPEG of the
same shot, and :func:`image_size` gives the size of the pixels :func:`read_image_float` returns.
"""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable, Iterator, List, Tuple

import numpy as np
import torch

from retinexgs.data.camera_raw import GPR_ADVICE, GPR_EXTENSIONS, is_raw_path, read_view_linear
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write
# The one list of readable types (retinexgs/formats.py, light enough for --help texts), re-exported here.
from retinexgs.formats import BAYER_RAW_EXTENSIONS, HEIF_EXTENSIONS, IMAGE_EXTENSIONS, readable_formats  # noqa: F401

RAW_EXTENSIONS = BAYER_RAW_EXTENSIONS  # camera raw types (read with rawpy, an install requirement)
# The image cache's copy of a raw view (float32 [H,W,3], extended sRGB encoding): readable, never listed as a photo.
FLOAT_CACHE_EXTENSION = ".npy"


def is_raw_file(path: Path) -> bool:
    """True when ``path``'s extension is a camera raw type (:data:`RAW_EXTENSIONS`, any case)."""
    return is_raw_path(path)


def no_images_reason(folder: Path) -> str:
    """Why ``folder`` has no readable photos, for a "no photos" message: the readable types, and the types of
    the files it does hold (e.g. a folder of camera RAW files) or that it is empty / missing."""
    folder = Path(folder)
    if not folder.is_dir():
        return f"{folder} is not a folder"
    kinds = sorted({p.suffix.lower() or "(no extension)" for p in folder.iterdir()
                    if p.is_file() and not p.name.startswith(".")})
    held = (f"it holds only {', '.join(kinds[:8])}{' ...' if len(kinds) > 8 else ''} files" if kinds
            else "it holds no files")
    if any(k in GPR_EXTENSIONS for k in kinds):  # say why GoPro raws are not read, and how to convert them
        return f"{held}: {GPR_ADVICE}"
    return f"photos are read from {readable_formats()}; {held}"


def is_image_file(path: Path) -> bool:
    """True for a regular file whose extension is a supported image type (case-insensitive)."""
    return path.is_file() and path.suffix.lower() in IMAGE_EXTENSIONS and not path.name.startswith(".")


def list_images(folder: Path) -> List[Path]:
    """Image files directly inside ``folder``, sorted by name (sub-folders are not searched)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted((p for p in folder.iterdir() if is_image_file(p)), key=lambda p: p.name)


_HEIF_REGISTERED = False


def _pil():
    """Pillow's Image module, with the HEIC/HEIF opener registered (once; lazily, so importing this module and
    commands that never open a photo stay fast)."""
    global _HEIF_REGISTERED
    try:
        from PIL import Image
    except ImportError as exc:  # pragma: no cover - pillow is a core dependency
        raise UserError("reading images needs Pillow: pip install pillow") from exc
    if not _HEIF_REGISTERED:
        try:
            from pillow_heif import register_heif_opener
        except ImportError:  # reading a HEIC then fails with the install line (_open)
            pass
        else:
            register_heif_opener()
        _HEIF_REGISTERED = True
    return Image


# Pillow's transpose that undoes what libheif did for each EXIF orientation value (the inverse of turning the
# stored pixels upright): 90° turns swap in the other direction, flips and transposes are their own inverse.
_UNDO_ORIENTATION = {2: "FLIP_LEFT_RIGHT", 3: "ROTATE_180", 4: "FLIP_TOP_BOTTOM", 5: "TRANSPOSE",
                     6: "ROTATE_90", 7: "TRANSVERSE", 8: "ROTATE_270"}


def _heif_turn(im) -> int:
    """The EXIF orientation (2-8) that the HEIF decoder applied to ``im``, or 1 (none; every other format)."""
    if im.format != "HEIF":
        return 1
    value = im.info.get("original_orientation")
    return int(value) if value in _UNDO_ORIENTATION else 1


@contextlib.contextmanager
def _open(path: Path) -> Iterator:
    """``Image.open(path)`` with the read errors of one file as UserError naming it."""
    Image = _pil()
    path = Path(path)
    try:
        with Image.open(path) as im:
            yield im
    except FileNotFoundError:
        raise UserError(f"image {path} does not exist") from None
    except UserError:
        raise
    except Exception as exc:  # Pillow raises several types for corrupt files
        if path.suffix.lower() in HEIF_EXTENSIONS and not _heif_available():
            raise UserError(f"cannot read {path}: reading HEIC/HEIF photos needs pillow-heif: "
                            "pip install pillow-heif") from None
        raise UserError(f"cannot read image {path}: {exc}") from None


def _heif_available() -> bool:
    try:
        import pillow_heif  # noqa: F401
    except ImportError:
        return False
    return True


def image_size(path: Path) -> Tuple[int, int]:
    """(width, height) of an image as :func:`read_image_float` returns it (stored orientation, see the module
    docstring), reading only its header; UserError if it cannot be read. A raw file: LibRaw's size of the
    visible area in whole 2x2 quads, without decoding the mosaic."""
    if is_raw_path(path):
        from retinexgs.data.camera_raw import read_header

        head = read_header(path)
        return head.width, head.height
    if _is_float_cache(path):
        h, w = _read_float_cache(path, header_only=True).shape[:2]
        return w, h
    with _open(path) as im:
        w, h = int(im.size[0]), int(im.size[1])
        return (h, w) if _heif_turn(im) >= 5 else (w, h)  # orientations 5-8 turn by 90°: undoing swaps sides


# Pillow modes holding one channel of 16-bit samples (``I`` is how some Pillow versions open them).
_SIXTEEN_BIT_GREY = ("I;16", "I;16L", "I;16B", "I;16N", "I")


def _bit_depth(path: Path, im) -> int:
    """Bits per sample of a PNG or TIFF as stored (Pillow's mode hides 16-bit RGB); 8 for other formats."""
    if im.format == "PNG":
        with open(path, "rb") as f:
            header = f.read(25)
        return header[24] if len(header) == 25 else 8  # IHDR bit depth
    if im.format == "TIFF":
        bits = im.tag_v2.get(258, (8,))  # BitsPerSample
        return int(bits[0] if isinstance(bits, tuple) else bits)
    return 8


def _decode_16bit_colour(path: Path) -> np.ndarray:
    """A 16-bit RGB(A) file as float32 [H,W,3] in [0,1] via OpenCV, or an empty array without OpenCV."""
    try:
        import cv2
    except ImportError:
        return np.empty(0, np.float32)
    data = cv2.imdecode(np.fromfile(str(path), np.uint8), cv2.IMREAD_UNCHANGED)
    if data is None or data.dtype != np.uint16 or data.ndim != 3 or data.shape[2] not in (3, 4):
        return np.empty(0, np.float32)
    return data[:, :, 2::-1].astype(np.float32) / 65535.0  # BGR(A) -> RGB, alpha dropped


def holds_unclipped(path: Path) -> bool:
    """True for a file whose values go beyond [0, 1] when read unclipped: a camera raw file or the float copy the
    undistort/downscale cache makes of one."""
    return is_raw_path(path) or _is_float_cache(Path(path))


def _is_float_cache(path: Path) -> bool:
    return Path(path).suffix.lower() == FLOAT_CACHE_EXTENSION


def _read_float_cache(path: Path, header_only: bool = False) -> np.ndarray:
    """The float32 [H,W,3] array of a cache ``.npy`` (memory-mapped and unchecked for finiteness when
    ``header_only``: only its shape is wanted); UserError (one line naming the file) for a missing, truncated or
    malformed file."""
    path = Path(path)
    try:
        a = np.load(path, mmap_mode="r" if header_only else None, allow_pickle=False)
    except FileNotFoundError:
        raise UserError(f"image {path} does not exist") from None
    except Exception as exc:  # numpy raises ValueError, EOFError, OSError... for a broken file
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserError(f"cannot read cached image {path}: {reason} (delete it to have it rebuilt)") from None
    if not isinstance(a, np.ndarray) or a.dtype != np.float32 or a.ndim != 3 or a.shape[2] != 3 or 0 in a.shape:
        what = (f"{a.dtype} {'x'.join(map(str, a.shape))}" if isinstance(a, np.ndarray) else type(a).__name__)
        raise UserError(f"cannot read cached image {path}: it holds {what}, not float32 HxWx3 "
                        "(delete it to have it rebuilt)")
    if header_only:
        return a
    if not np.isfinite(a).all():
        raise UserError(f"cannot read cached image {path}: it holds non-finite values (delete it to have it rebuilt)")
    return np.ascontiguousarray(a)


def read_image_float(path: Path, unclipped: bool = False) -> np.ndarray:
    """Read an image as float32 [H,W,3] in [0,1] scaled by its bit depth (see the module docstring);
    UserError naming the file if it is missing, unreadable or of an unsupported pixel format. A camera raw
    file is read as a scene view, a cache ``.npy`` as stored (see the module docstring); for those two
    ``unclipped=True`` keeps values outside [0, 1] (extended sRGB encoding), other images ignore it."""
    path = Path(path)
    if is_raw_path(path):
        from retinexgs.data.camera_raw import read_view_srgb

        return read_view_srgb(path, clip=not unclipped)
    if _is_float_cache(path):
        values = _read_float_cache(path)
        # clipping the extended encoding equals encoding clipped light: the curve is monotone, 0 -> 0, 1 -> 1
        return values if unclipped else np.clip(values, 0.0, 1.0)
    Image = _pil()
    try:
        with _open(path) as opened:
            opened.load()
            im = opened
            turn = _heif_turn(im)
            if turn != 1:  # the decoder turned it upright: back to the stored pixels, as for JPEG
                im = im.transpose(getattr(Image.Transpose, _UNDO_ORIENTATION[turn]))
            mode = im.mode
            if mode in _SIXTEEN_BIT_GREY:
                grey = np.asarray(im)
                if grey.min() < 0 or grey.max() > 65535:
                    raise UserError(f"cannot read image {path}: 32-bit integer pixels are not supported "
                                    "(save it as 8- or 16-bit)")
                return np.repeat((grey.astype(np.float32) / 65535.0)[:, :, None], 3, axis=2)
            if mode == "F":
                raise UserError(f"cannot read image {path}: floating-point pixels are not supported "
                                "(save it as 8- or 16-bit)")
            if mode in ("RGB", "RGBA") and _bit_depth(path, im) == 16:
                deep = _decode_16bit_colour(path)
                if deep.shape[:2] == (im.size[1], im.size[0]):
                    return deep
            rgb = np.asarray(im.convert("RGB"), dtype=np.uint8)
    except UserError:
        raise
    except Exception as exc:
        raise UserError(f"cannot read image {path}: {exc}") from None
    return rgb.astype(np.float32) / 255.0


def read_image_for_part(path: Path, part: Callable[[np.ndarray], np.ndarray]) -> Tuple[np.ndarray, bool]:
    """(image, whether any value of the whole image is above 0) for a reader that uses only ``part`` of
    :func:`read_image_float`'s image (``part``: the slicing of an [H,W,3] array it applies, e.g. a centre crop). A
    camera raw file's view is sRGB-encoded only in ``part`` (per value: the same bits as the whole view's; ~1 s less
    a 12 MP view) and returned as that part, a view with the whole image's strides (numpy's sums follow the memory
    layout: a reduction over it gives the same figures to the last bit); another image is returned whole (decoded
    whole anyway; a reader may crop it otherwise, e.g. on its JPEG block grid)."""
    path = Path(path)
    if not is_raw_path(path):
        image = read_image_float(path)
        return image, bool(np.any(image > 0))
    from retinexgs.data.srgb import linear_to_srgb

    rgb = read_view_linear(path)
    lit = bool(np.any(rgb > 0))  # the view is above 0 exactly where its light is (the curve: 0 -> 0, increasing)
    whole = np.empty_like(rgb)  # only the part is written (and its pages touched)
    out = part(whole)
    out[...] = linear_to_srgb(np.ascontiguousarray(part(rgb)))  # contiguous: numpy's vector loops, as the whole
    return out, lit


def read_image(path: Path) -> np.ndarray:
    """Read an image as uint8 [H,W,3] RGB (16-bit input rounded to 8 bits); UserError naming the file if
    it is missing or unreadable."""
    return np.clip(np.rint(read_image_float(path) * 255.0), 0, 255).astype(np.uint8)


def load_image_tensor(path: Path, unclipped: bool = False) -> torch.Tensor:
    """Read an image as a float32 [H,W,3] tensor in [0,1] (full bit depth); ``unclipped`` as for
    :func:`read_image_float`."""
    return torch.from_numpy(read_image_float(path, unclipped))


def write_image_atomic(path: Path, rgb: np.ndarray, quality: int = 95) -> None:
    """Write uint8 [H,W,3] RGB to ``path`` through a temporary file and ``os.replace``.

    The format follows the extension; a reader never sees a half-written file.
    """
    Image = _pil()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fmt = {".jpg": "JPEG", ".jpeg": "JPEG", ".png": "PNG", ".bmp": "BMP", ".tif": "TIFF", ".tiff": "TIFF",
           ".webp": "WEBP"}.get(path.suffix.lower(), "PNG")

    def write(f) -> None:
        # fast PNG compression: caches are rewritten rarely but read often, size matters little
        kwargs = {"quality": quality} if fmt in ("JPEG", "WEBP") else {"compress_level": 1} if fmt == "PNG" else {}
        Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), "RGB").save(f, format=fmt, **kwargs)

    atomic_write(path, write)


def resize_image(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-average (box filter) resize of uint8 RGB to ``width`` x ``height``.

    Pillow's box filter maps pixel centres consistently with the pixel-centre convention, so intrinsics
    scale by exactly new_size / old_size (fx, cx alike).
    """
    Image = _pil()
    if rgb.shape[1] == width and rgb.shape[0] == height:
        return rgb
    return np.asarray(Image.fromarray(rgb, "RGB").resize((int(width), int(height)), Image.BOX))


def is_fresh(cached: Path, *sources: Path) -> bool:
    """True when ``cached`` exists and is at least as new as every source file."""
    try:
        t = cached.stat().st_mtime_ns
    except FileNotFoundError:
        return False
    return all(t >= s.stat().st_mtime_ns for s in sources)
