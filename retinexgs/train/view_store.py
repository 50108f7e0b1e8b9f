"""The view store: a scene's training views on the host as one memory-mapped file (:class:`ViewStore`) of
compact photos (uint8, or uint16 for 16-bit sources; float16 for camera raw views; float32 for a reader that scales
otherwise) and 2D priors
(R and L as the decomposition cache's float16), 11 B per view-pixel; its fingerprint, path, size estimate and
the free-space check before it is written. Lossless: see :mod:`retinexgs.train.views`.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np
from torch import Tensor

from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write, free_bytes


# ---- compact photos -----------------------------------------------------------------------------------------

PHOTO_LEVELS = {"uint8": 255, "uint16": 65535}


def photo_table(dtype: str) -> np.ndarray:
    """float32 [levels + 1]: the value of each integer sample as the image reader scales it (k / 255 or
    k / 65535 in float32, :func:`retinexgs.data.images.read_image_float`)."""
    n = PHOTO_LEVELS[dtype]
    return np.arange(n + 1, dtype=np.int64).astype(np.float32) / float(n)


_PROBE_VALUES = 4096  # values of a photo that compact_photo checks before the whole


def _all_levels(a: np.ndarray, dtype: str) -> bool:
    """Whether every value of float32 ``a`` is one of ``dtype``'s levels as the reader scales them."""
    n = PHOTO_LEVELS[dtype]
    return bool(np.array_equal(photo_table(dtype)[np.clip(np.rint(a * n), 0, n).astype(dtype)], a))


def compact_photo(image: Tensor) -> np.ndarray:
    """A photo read as float32 [H,W,3] in its smallest exact form: uint8 when every value is k / 255, uint16
    when k / 65535, float16 when every value is one (a camera raw view's target, ``View.load_target``), else
    float32 (a reader that scales otherwise)."""
    a = np.ascontiguousarray(image.detach().cpu().numpy(), dtype=np.float32)
    # A sample of the values first: where one of them is not k / n, the whole photo is not either (a raw view's
    # target fails both integer forms at its first values; the full tests cost ~1 s a 12 MP view).
    probe = a.reshape(-1)[::max(1, a.size // _PROBE_VALUES)]
    for name in ("uint8", "uint16"):
        n = PHOTO_LEVELS[name]
        if not _all_levels(probe, name):
            continue
        k = np.clip(np.rint(a * n), 0, n).astype(name)
        if np.array_equal(photo_table(name)[k], a):
            return k
    with np.errstate(over="ignore"):
        half = a.astype(np.float16)
    if np.array_equal(half.astype(np.float32), a):
        return half
    return a


# ---- the host store -----------------------------------------------------------------------------------------

_MAGIC = b"RGSVIEWS"
_FORMAT = 1
# What a stored photo holds, part of the fingerprint, so that a store made before is rebuilt rather than read as
# the new values: 2, camera raw views stored unclipped (issue 52 stage 3b); 3, their targets rounded to float16.
_PHOTOS = 3
_PREFIX = struct.Struct("<8sIQQ")  # magic, format, header offset, header length
_PAGE = 4096  # each view starts on a page
_ALIGN = 256  # each array within a view


def _up(n: int, a: int) -> int:
    return (n + a - 1) // a * a


@dataclass
class StoredView:
    """Where one view lies in a :class:`ViewStore`: its span [start, start + nbytes) of the file and, within
    it, the photo (``photo_dtype`` [H,W,3]) and the priors R (float16 [H,W,3]) and L (float16 [H,W,1]) at
    byte offsets (-1: no priors)."""

    name: str
    height: int
    width: int
    photo_dtype: str
    start: int
    nbytes: int
    photo: int
    R: int
    L: int


def _layout(height: int, width: int, photo_dtype: str, priors: bool) -> Tuple[int, int, int, int]:
    """(photo, R, L offsets within a view's span, span bytes)."""
    px = height * width
    photo_bytes = px * 3 * np.dtype(photo_dtype).itemsize
    r = _up(photo_bytes, _ALIGN) if priors else -1
    l = r + _up(px * 3 * 2, _ALIGN) if priors else -1
    end = l + px * 2 if priors else photo_bytes
    return 0, r, l, end


def store_size_estimate(sizes: Sequence[Tuple[int, int]], priors: bool) -> int:
    """Bytes of a store of views of these (height, width), 8-bit photos."""
    return _PAGE + sum(_up(_layout(h, w, "uint8", priors)[3], _PAGE) for h, w in sizes) + 65536


class ViewStore:
    """Photos and 2D priors of a scene's training views in one file, memory-mapped read-only. Layout: a
    prefix (magic ``RGSVIEWS``, format, header offset and length), each view's span on a page boundary (photo,
    then R, then L, see :class:`StoredView`), and a JSON header at the end (format, fingerprint, the views).
    Written atomically by :meth:`build` (temporary file, fsync, rename); :meth:`open` trusts a file only when
    its fingerprint (:func:`store_fingerprint`) and size match."""

    def __init__(self, path: Path, header: Dict) -> None:
        self.path = Path(path)
        self.fingerprint: str = header["fingerprint"]
        self.priors: bool = bool(header["priors"])
        self.views = [StoredView(**v) for v in header["views"]]
        self._map = np.memmap(self.path, dtype=np.uint8, mode="r")

    def __len__(self) -> int:
        return len(self.views)

    @property
    def nbytes(self) -> int:
        return int(self._map.shape[0])

    def span(self, i: int) -> np.ndarray:
        """View ``i``'s bytes (a read-only view of the mapping)."""
        v = self.views[i]
        return self._map[v.start:v.start + v.nbytes]

    def read_into(self, out: np.ndarray) -> None:
        """The whole file's bytes into ``out`` (uint8, :attr:`nbytes` long), read in 64 MiB pieces."""
        if out.shape != (self.nbytes,) or out.dtype != np.uint8:
            raise ValueError(f"read_into needs a uint8 array of {self.nbytes} bytes, got {out.dtype} {out.shape}")
        step = 64 << 20
        for at in range(0, self.nbytes, step):
            np.copyto(out[at:at + step], self._map[at:at + step])

    def photo(self, i: int) -> np.ndarray:
        v = self.views[i]
        n = v.height * v.width * 3 * np.dtype(v.photo_dtype).itemsize
        return self.span(i)[v.photo:v.photo + n].view(v.photo_dtype).reshape(v.height, v.width, 3)

    def priors_of(self, i: int) -> Tuple[Optional[np.ndarray], Optional[np.ndarray]]:
        """(R float16 [H,W,3], L float16 [H,W,1]) of view ``i``, or (None, None)."""
        v = self.views[i]
        if v.R < 0:
            return None, None
        px = v.height * v.width
        span = self.span(i)
        R = span[v.R:v.R + px * 6].view(np.float16).reshape(v.height, v.width, 3)
        L = span[v.L:v.L + px * 2].view(np.float16).reshape(v.height, v.width, 1)
        return R, L

    def close(self) -> None:
        mm = getattr(self._map, "_mmap", None)
        self._map = None  # type: ignore[assignment]
        if mm is not None:
            try:
                mm.close()
            except BufferError:  # an array still points into it: the mapping goes with the last one
                pass

    @staticmethod
    def read_header(path: Path) -> Optional[Dict]:
        """The header of a store file, or None when it is missing, cut short or not a store."""
        try:
            with open(path, "rb") as f:
                prefix = f.read(_PREFIX.size)
                if len(prefix) != _PREFIX.size:
                    return None
                magic, fmt, offset, length = _PREFIX.unpack(prefix)
                if magic != _MAGIC or fmt != _FORMAT or offset + length != os.fstat(f.fileno()).st_size:
                    return None
                f.seek(offset)
                header = json.loads(f.read(length).decode("utf-8"))
        except (OSError, ValueError):
            return None
        return header if isinstance(header, dict) and header.get("format") == _FORMAT else None

    @classmethod
    def open(cls, path: Path, fingerprint: str) -> Optional["ViewStore"]:
        """The store at ``path`` when it holds exactly what ``fingerprint`` describes; else None."""
        header = cls.read_header(path)
        if header is None or header.get("fingerprint") != fingerprint:
            return None
        try:
            views = header["views"]
            end = max((v["start"] + v["nbytes"] for v in views), default=0)
            if end > Path(path).stat().st_size:
                return None
            return cls(path, header)
        except (OSError, KeyError, TypeError, ValueError):
            return None

    @classmethod
    def build(cls, path: Path, fingerprint: str, priors: bool,
              items: Iterable[Tuple[str, np.ndarray, Optional[np.ndarray], Optional[np.ndarray]]],
              elsewhere: str = "") -> "ViewStore":
        """Write the store from ``items`` (name, photo [H,W,3] uint8 / uint16 / float32, R float16 [H,W,3],
        L float16 [H,W,1], or None without priors), consumed one at a time, then open it. Atomic: an error or
        a kill leaves no store (at worst a ``.tmp-`` file); a full or read-only disk raises a UserError naming
        ``elsewhere`` (how to put it on another disk)."""
        records: List[Dict] = []

        def write(f) -> None:
            f.write(b"\0" * _PAGE)
            pos = _PAGE
            for name, photo, R, L in items:
                h, w = photo.shape[:2]
                off_photo, off_r, off_l, nbytes = _layout(h, w, photo.dtype.name, priors)
                parts = [(off_photo, photo)] + ([(off_r, R), (off_l, L)] if priors else [])
                at = 0
                for off, arr in parts:
                    if off > at:
                        f.write(b"\0" * (off - at))
                    data = np.ascontiguousarray(arr)
                    f.write(memoryview(data).cast("B"))
                    at = off + data.nbytes
                pad = _up(nbytes, _PAGE) - nbytes
                f.write(b"\0" * pad)
                records.append({"name": name, "height": h, "width": w, "photo_dtype": photo.dtype.name,
                                "start": pos, "nbytes": nbytes, "photo": off_photo, "R": off_r, "L": off_l})
                pos += nbytes + pad
            header = json.dumps({"format": _FORMAT, "fingerprint": fingerprint, "priors": priors,
                                 "views": records}).encode("utf-8")
            f.write(header)
            f.seek(0)
            f.write(_PREFIX.pack(_MAGIC, _FORMAT, pos, len(header)))

        try:
            atomic_write(path, write, elsewhere=elsewhere)
        except OSError as exc:
            if exc.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
                raise
            where = f"; put it elsewhere with {elsewhere}" if elsewhere else ""
            raise UserError(f"cannot write the view store {path}: {exc.strerror or exc}{where}") from None
        store = cls.open(path, fingerprint)
        if store is None:  # pragma: no cover - what was just written must read back
            raise UserError(f"the view store {path} did not read back after writing it")
        return store


def store_fingerprint(image_paths: Sequence[Path], sizes: Sequence[Tuple[int, int]], priors_tag: str) -> str:
    """What a store must match to be reused: the format, the priors' settings (``<method>-<key>`` of the
    decomposition cache, or ``none``) and per view its photo's content (SHA-256 of the file's bytes, hashed once
    per process while the file is unchanged, :func:`retinexgs.data.undistort.source_digest`) and size. An
    edited, regenerated or resized photo, or other settings, make a new store; a photo replaced by another with
    an older modification time (``cp -p``, ``rsync -a``, unzip) too."""
    from retinexgs.data.undistort import image_key  # the shared, memoised content key

    items = [[image_key(Path(p)), int(Path(p).stat().st_size), int(h), int(w)]
             for p, (h, w) in zip(image_paths, sizes)]
    blob = json.dumps({"format": _FORMAT, "photos": _PHOTOS, "key": "content", "priors": priors_tag, "views": items},
                      sort_keys=True)
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def store_tag(priors: str, raw_preview: bool = False, balance: Optional[Sequence[float]] = None) -> str:
    """The store's settings tag: the priors' (``<method>-<key>`` or ``none``), then what else changes the stored
    values for the same photo files: priors from the raw views' denoised preview
    (``decomposer.raw.preview_denoise``), and the photos' white balance (``data.white_balance``, its gains hashed).
    Without these a store made with other settings would be reused for the same files."""
    parts = [priors]
    if raw_preview:
        parts.append("rawpreview")
    if balance is not None:
        gains = ",".join(f"{float(v):.9g}" for v in balance)
        parts.append("wb" + hashlib.sha256(gains.encode("utf-8")).hexdigest()[:8])
    return "-".join(parts)


def store_path(cache_root: Path, image_paths: Sequence[Path], priors_tag: str) -> Path:
    """``<cache root>/views-<priors tag>-<8 hex of the photos' paths>.bin``: one store per scene view list and
    prior settings, replaced in place when its photos change."""
    digest = hashlib.sha256("\n".join(str(Path(p).resolve()) for p in image_paths).encode("utf-8")).hexdigest()
    return Path(cache_root) / f"views-{priors_tag}-{digest[:8]}.bin"


def check_store_space(path: Path, nbytes: int, hint: str) -> None:
    """Refuse, before any decoding, a store that cannot fit on its disk."""
    free = free_bytes(path.parent)
    if free is not None and free < nbytes:
        raise UserError(f"no space left on device for the view store {path}: it needs {nbytes / 2**30:.2f} GiB, "
                        f"{free / 2**30:.2f} GiB are free; {hint}")



__all__ = ["PHOTO_LEVELS", "photo_table", "compact_photo", "StoredView", "ViewStore", "store_size_estimate", "store_tag",
           "store_fingerprint", "store_path", "check_store_space"]
