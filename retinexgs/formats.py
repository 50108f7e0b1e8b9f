"""The photo file types RetinexGS reads: the one list every command, message and help text uses.

A leaf module (no imports beyond the standard library), so that a sub-command's ``--help`` can name the types
without loading the readers (:mod:`retinexgs.data.images` pulls in torch). Every extension is compared in lower
case: ``.HEIC``, ``.JPG`` and ``.jpg`` alike.
"""
from __future__ import annotations

from typing import Tuple

# Camera raw types whose cameras LibRaw reads as a 2x2 Bayer mosaic (read with rawpy, an install requirement).
# .raf is kept although most Fujifilm X bodies are X-Trans (the raw reader refuses those with one line naming
# the sensor); Sigma .x3f (Foveon, never Bayer) and the rarer medium-format/legacy types LibRaw also reads are
# left out (retinexgs.data.camera_raw.RAW_EXTENSIONS).
BAYER_RAW_EXTENSIONS: Tuple[str, ...] = (".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2",
                                         ".raf", ".orf", ".rw2", ".pef", ".srw")
# A phone's default: read through pillow-heif (an install requirement).
HEIF_EXTENSIONS: Tuple[str, ...] = (".heic", ".heif")
# Types Pillow reads and writes itself.
PLAIN_EXTENSIONS: Tuple[str, ...] = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
# Every readable photo type: what a folder of photos, a transforms JSON's frame or a COLMAP image may be.
IMAGE_EXTENSIONS: Tuple[str, ...] = PLAIN_EXTENSIONS + HEIF_EXTENSIONS + BAYER_RAW_EXTENSIONS


def readable_formats() -> str:
    """The readable file types for messages and help texts: ".jpg, .jpeg, ... .srw (any case)"."""
    return ", ".join(IMAGE_EXTENSIONS) + " (any case)"
