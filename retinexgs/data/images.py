"""Image files: listing, reading (with clear errors), atomic writing and resizing.

Images are read with Pillow as 8-bit RGB (greyscale and RGBA are converted; EXIF orientation is ignored,
as COLMAP ignores it, so poses and pixels stay consistent).
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Tuple

import numpy as np
import torch

from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")


def is_image_file(path: Path) -> bool:
    """True for a regular file whose extension is a supported image type (case-insensitive)."""
    return path.is_file() and path.suffix.lower() in IMAGE_EXTENSIONS and not path.name.startswith(".")


def list_images(folder: Path) -> List[Path]:
    """Image files directly inside ``folder``, sorted by name (sub-folders are not searched)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted((p for p in folder.iterdir() if is_image_file(p)), key=lambda p: p.name)


def _pil():
    try:
        from PIL import Image
    except ImportError as exc:  # pragma: no cover - pillow is a core dependency
        raise UserError("reading images needs Pillow: pip install pillow") from exc
    return Image


def image_size(path: Path) -> Tuple[int, int]:
    """(width, height) of an image, reading only its header; UserError if it cannot be read."""
    Image = _pil()
    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except FileNotFoundError:
        raise UserError(f"image {path} does not exist") from None
    except Exception as exc:  # Pillow raises several types for corrupt files
        raise UserError(f"cannot read image {path}: {exc}") from None


def read_image(path: Path) -> np.ndarray:
    """Read an image as uint8 [H,W,3] RGB; UserError naming the file if it is missing or unreadable."""
    Image = _pil()
    try:
        with Image.open(path) as im:
            im.load()
            rgb = im.convert("RGB")
    except FileNotFoundError:
        raise UserError(f"image {path} does not exist") from None
    except Exception as exc:
        raise UserError(f"cannot read image {path}: {exc}") from None
    return np.asarray(rgb, dtype=np.uint8)


def load_image_tensor(path: Path) -> torch.Tensor:
    """Read an image as a float32 [H,W,3] tensor in [0,1]."""
    return torch.from_numpy(read_image(path).astype(np.float32) / 255.0)


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
