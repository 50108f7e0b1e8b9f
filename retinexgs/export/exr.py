"""Scene-linear OpenEXR files (``render --format exr``): float32 RGB, Rec.709 primaries and D65 white in the
``chromaticities`` attribute, ZIP compression (lossless), written atomically.

The OpenEXR bindings are an optional extra (``pip install "retinexgs[hdr]"``); :func:`need_openexr` says so in
one line, before any work, when they are missing.
"""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch

from retinexgs.errors import UserError
from retinexgs.fileio import TMP_PREFIX, atomic_write, make_folders, remove_empty_folders

# Rec.709 / sRGB primaries and white (x, y of red, green, blue, white): what the linear values mean.
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)


def need_openexr(what: str = "render --format exr"):
    """The ``OpenEXR`` module; a UserError with the install line when it is missing (or too old for its
    ``OpenEXR.File`` API, OpenEXR 3.3)."""
    try:
        import OpenEXR
    except ImportError:
        OpenEXR = None
    if OpenEXR is None or not hasattr(OpenEXR, "File"):
        raise UserError(f'{what} needs OpenEXR (3.3 or newer): pip install "retinexgs[hdr]" '
                        "(or pip install openexr)")
    return OpenEXR


def write_exr(path: Path, image, attributes: Optional[Dict[str, str]] = None) -> Path:
    """Write ``image`` [H,W,3] (a tensor or an array; linear light) as a float32 RGB OpenEXR file at ``path``,
    atomically; ``attributes``: extra string attributes of the header (what the values mean, the edits used).
    The library writes to a file name, so the file is made in a temporary folder beside ``path`` and copied
    through :func:`retinexgs.fileio.atomic_write` (an interrupted write never leaves a truncated file)."""
    OpenEXR = need_openexr()
    arr = image.detach().float().cpu().numpy() if torch.is_tensor(image) else np.asarray(image, np.float32)
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise ValueError(f"write_exr needs an [H,W,3] image, got shape {tuple(arr.shape)}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "chromaticities": REC709_CHROMATICITIES}
    header.update({str(k): str(v) for k, v in (attributes or {}).items()})
    path = Path(path)
    made = make_folders(path.parent)
    try:
        with tempfile.TemporaryDirectory(prefix=TMP_PREFIX, dir=path.parent) as tmp:
            tmp_file = Path(tmp) / "image.exr"
            with OpenEXR.File(header, {"RGB": arr}) as f:
                f.write(str(tmp_file))
            with open(tmp_file, "rb") as f_in:
                atomic_write(path, lambda f_out: shutil.copyfileobj(f_in, f_out))
    except BaseException:
        remove_empty_folders(made)  # a failed first frame leaves no empty OUT/<map>/ behind
        raise
    return path


def read_exr(path: Path) -> np.ndarray:
    """[H,W,3] float32 RGB of an OpenEXR file (as :func:`write_exr` writes it)."""
    OpenEXR = need_openexr("reading OpenEXR")
    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        if "RGB" in channels:
            return np.asarray(channels["RGB"].pixels, dtype=np.float32)
        return np.stack([np.asarray(channels[c].pixels, dtype=np.float32) for c in "RGB"], axis=-1)


def read_exr_header(path: Path) -> Dict:
    """The header of an OpenEXR file (its attributes by name)."""
    OpenEXR = need_openexr("reading OpenEXR")
    with OpenEXR.File(str(path), header_only=True) as f:
        return dict(f.header())
