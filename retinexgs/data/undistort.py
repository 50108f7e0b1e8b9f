"""Undistortion and downscaling of input images into the scene's cache.

A distorted camera (any non-zero OpenCV coefficient) is replaced by a pinhole camera of the same size
whose intrinsics come from OpenCV's ``getOptimalNewCameraMatrix`` with ``alpha=0``: every output pixel
sees real image content (no black borders), at the price of a slight crop. Images are remapped with
bilinear interpolation, then (for ``downscale > 1``) box-filtered to ``round(size / downscale)``; the
intrinsics are scaled by new_size / old_size in the pixel-centre convention.

Results are cached as PNG under ``<cache>/undistorted/<camera-key>_x<downscale>/`` (or
``<cache>/downscaled/...`` when only resizing), mirroring the source's path relative to the scene
folder with the first 16 hex digits of the SHA-256 of the source's bytes added to the name
(``low/0001.jpg`` -> ``low/0001-<16 hex>.png``). A camera raw view is cached as ``.npy`` instead
(``low/0001.dng`` -> ``low/0001-<16 hex>.npy``, float32, its unclipped values in the extended sRGB encoding, see
:mod:`retinexgs.data.images`), remapped and box-filtered in LINEAR light: an average of encoded values would bias
the mean of the noise around black, which training in linear light needs zero-mean. Copies are written
atomically (all of a load's files together, see :func:`process_all`). A cached copy is reused only when it
exists under that name: the key is the source's content plus the camera and downscale settings (the folder),
never a path or a modification time, so two scenes that share a ``data.cache_dir`` and a file name, or a photo
replaced by another with an older mtime (``cp -p``, ``rsync -a``, unzip), each get their own pixels. Copies of
older contents are not deleted here.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from functools import lru_cache
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from retinexgs.data.camera import Intrinsics
from retinexgs.data.camera_raw import folder_exposure, is_raw_path, read_view_linear
from retinexgs.data.images import FLOAT_CACHE_EXTENSION, read_image, resize_image
from retinexgs.data.srgb import linear_to_srgb_extended
from retinexgs.errors import UserError
from retinexgs.fileio import TMP_PREFIX, atomic_write, content_digest

# How a full or read-only disk names the option that moves the image cache (train's spelling by default).
DEFAULT_ELSEWHERE = "--set data.cache_dir=DIR"
_DIGEST_LEN = 16
# Source digests of this process, keyed by what a replacement of the file always changes (inode, size, mtime and
# ctime: ``cp -p`` or ``os.utime`` can set an old mtime but not the ctime), so a photo is read once per process.
_digests: Dict[Tuple[str, int, int, int, int, int], str] = {}
_digests_lock = threading.Lock()


def source_digest(path: Path) -> str:
    """The first 16 hex digits of the SHA-256 of ``path``'s bytes (:func:`retinexgs.fileio.content_digest`),
    memoised within the process while the file is unchanged; UserError naming the file if it cannot be read."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise UserError(f"cannot read image {path}: {exc.strerror or exc}") from None
    key = (str(Path(path).resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    with _digests_lock:
        hit = _digests.get(key)
    if hit is not None:
        return hit
    try:
        digest = content_digest(path, _DIGEST_LEN)
    except OSError as exc:
        raise UserError(f"cannot read image {path}: {exc.strerror or exc}") from None
    with _digests_lock:
        _digests[key] = digest
    return digest


def image_key(path: Path) -> str:
    """What every cache of a photo is keyed by: :func:`source_digest`, and for a camera raw file also the exposure
    factor it is read with (its folder's reference exposure, retinexgs.data.camera_raw.folder_exposure), which a
    new raw file of another exposure in the folder changes: the same bytes then read as other pixels."""
    digest = source_digest(path)
    if not is_raw_path(path):
        return digest
    factor = folder_exposure(Path(path).parent).factors.get(Path(path).name, 1.0)
    return hashlib.sha256(f"{digest}:{factor:.9g}".encode()).hexdigest()[:_DIGEST_LEN]


def _cv2():
    try:
        import cv2
    except ImportError:
        raise UserError("undistorting images needs OpenCV: pip install opencv-contrib-python-headless "
                        "(or opencv-python-headless)") from None
    return cv2


def undistorted_camera(cam: Intrinsics) -> Intrinsics:
    """The pinhole camera (same size) that :func:`undistort_rgb` produces for ``cam``."""
    if not cam.is_distorted:
        return replace(cam, dist=())
    cv2 = _cv2()
    size = (cam.width, cam.height)
    newK, _ = cv2.getOptimalNewCameraMatrix(cam.K_opencv(), np.asarray(cam.dist, np.float64), size, 0.0, size)
    # back from OpenCV's integer-centre convention to pixel-centre convention
    return Intrinsics(cam.width, cam.height, float(newK[0, 0]), float(newK[1, 1]),
                  float(newK[0, 2]) + 0.5, float(newK[1, 2]) + 0.5, ())


@lru_cache(maxsize=8)
def _maps(cam: Intrinsics, new_cam: Intrinsics) -> Tuple[np.ndarray, np.ndarray]:
    cv2 = _cv2()
    return cv2.initUndistortRectifyMap(cam.K_opencv(), np.asarray(cam.dist, np.float64), None,
                                       new_cam.K_opencv(), (new_cam.width, new_cam.height), cv2.CV_32FC1)


def undistort_rgb(rgb: np.ndarray, cam: Intrinsics, new_cam: Intrinsics) -> np.ndarray:
    """Remap a distorted uint8 or float32 RGB image taken by ``cam`` to the pinhole camera ``new_cam``
    (bilinear, border pixels replicated; float values outside [0, 1] are kept)."""
    cv2 = _cv2()
    if rgb.shape[:2] != (cam.height, cam.width):
        raise ValueError(f"image is {rgb.shape[1]}x{rgb.shape[0]}, camera is {cam.width}x{cam.height}")
    map1, map2 = _maps(cam, new_cam)
    return cv2.remap(rgb, map1, map2, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def output_camera(cam: Intrinsics, downscale: float) -> Intrinsics:
    """Pinhole camera of the cached images: undistorted, then resized by ``1/downscale``."""
    out = undistorted_camera(cam)
    if downscale != 1:
        w = max(1, int(round(cam.width / downscale)))
        h = max(1, int(round(cam.height / downscale)))
        out = out.scaled(w, h)
    return out


def needs_processing(cam: Intrinsics, downscale: float) -> bool:
    """True when images of ``cam`` must be rewritten (distorted, or resized)."""
    return cam.is_distorted or downscale != 1


def cache_path_for(src: Path, root: Path, cache_dir: Path, cam: Intrinsics, downscale: float,
                   digest: Optional[str] = None) -> Path:
    """Where the processed copy of ``src`` lives in the cache: a PNG (a ``.npy`` for a camera raw source, see the
    module docstring) that mirrors the path under ``root``, named with the source's key (``digest``, computed when
    not given; :func:`image_key`) in a folder named by the camera and the downscale."""
    digest = digest or image_key(src)
    kind = "undistorted" if cam.is_distorted else "downscaled"
    tag = f"{cam.key()}_x{downscale:g}"
    src = Path(src).resolve()
    try:
        rel = src.relative_to(Path(root).resolve())
    except ValueError:  # image outside the scene folder: keep names apart by their folder's hash
        rel = Path("external") / hashlib.sha1(str(src.parent).encode()).hexdigest()[:10] / src.name
    suffix = FLOAT_CACHE_EXTENSION if is_raw_path(src) else ".png"
    return Path(cache_dir) / kind / tag / rel.with_name(f"{rel.stem}-{digest}{suffix}")


def _write_png(path: Path, rgb: np.ndarray, elsewhere: str) -> None:
    from PIL import Image

    # fast PNG compression: a cache is written once and read often, its size matters little
    atomic_write(path, lambda f: Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), "RGB").save(
        f, format="PNG", compress_level=1), elsewhere=elsewhere)


def _write_npy(path: Path, values: np.ndarray, elsewhere: str) -> None:
    array = np.ascontiguousarray(values, dtype=np.float32)
    atomic_write(path, lambda f: np.save(f, array, allow_pickle=False), elsewhere=elsewhere)


def resize_linear(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-average resize of float32 [H,W,3] (linear light, any values) to ``width`` x ``height``: for whole
    factors per side exactly the mean of each block (in float64, then float32), else OpenCV's INTER_AREA."""
    h, w = rgb.shape[:2]
    if (w, h) == (width, height):
        return rgb
    if h % height == 0 and w % width == 0:
        blocks = rgb.astype(np.float64).reshape(height, h // height, width, w // width, rgb.shape[2])
        return blocks.mean(axis=(1, 3)).astype(np.float32)
    cv2 = _cv2()
    return cv2.resize(np.ascontiguousarray(rgb, dtype=np.float32), (int(width), int(height)),
                      interpolation=cv2.INTER_AREA)


def _check_size(src: Path, shape: Tuple[int, ...], cam: Intrinsics) -> None:
    if shape[:2] != (cam.height, cam.width):
        raise UserError(f"image {src} is {shape[1]}x{shape[0]} pixels but its camera says "
                        f"{cam.width}x{cam.height}")


def _process_raw(src: Path, dst: Path, cam: Intrinsics, out_cam: Intrinsics, elsewhere: str) -> None:
    """A raw view's copy: its unclipped values, remapped and resized in linear light, stored extended-encoded."""
    light = read_view_linear(src)  # the light read_image_float encodes: no encode-decode round trip (~1 s at 12 MP)
    _check_size(src, light.shape, cam)
    if cam.is_distorted:
        light = undistort_rgb(light, cam, undistorted_camera(cam))
    light = resize_linear(light, out_cam.width, out_cam.height)
    _write_npy(dst, linear_to_srgb_extended(light), elsewhere)


def process_image(src: Path, dst: Path, cam: Intrinsics, out_cam: Intrinsics, elsewhere: str = DEFAULT_ELSEWHERE) -> None:
    """Undistort/resize ``src`` (taken by ``cam``) into ``dst`` for ``out_cam``, unless ``dst`` exists (its
    name holds the source's content digest and its folder the settings: an existing file is this content's).
    A camera raw source gives a float ``.npy`` (see the module docstring), any other photo an 8-bit PNG.
    ``elsewhere``: the caller's option for moving the cache, named when the disk is full."""
    if dst.is_file():
        return
    if is_raw_path(src):
        _process_raw(src, dst, cam, out_cam, elsewhere)
        return
    rgb = read_image(src)
    if tuple(rgb.shape[:2]) in ((cam.height + 1, cam.width), (cam.height, cam.width + 1),
                                (cam.height + 1, cam.width + 1)):
        # The truth of a raw view whose odd last row/column was dropped (data.load._fit_camera: its camera is the
        # top-left crop of the sensor; every other size mismatch was rescaled there): cropped alike, before the
        # undistortion, so both remap with one camera.
        rgb = rgb[:cam.height, :cam.width]
    _check_size(src, rgb.shape, cam)
    if cam.is_distorted:
        rgb = undistort_rgb(rgb, cam, undistorted_camera(cam))
    rgb = resize_image(rgb, out_cam.width, out_cam.height)
    _write_png(dst, rgb, elsewhere)


def process_all(jobs: List[Tuple[Path, Path, Intrinsics, Intrinsics]], cache_dir: Path, workers: Optional[int] = None,
                elsewhere: str = DEFAULT_ELSEWHERE) -> None:
    """Run :func:`process_image` on (src, dst, cam, out_cam) jobs, a few threads at a time.

    All outputs (every ``dst`` lies under ``cache_dir``) are written into a temporary folder inside
    ``cache_dir`` and moved into place only when every job succeeded: a failure (an unreadable photo, a
    size mismatch, an interrupt) leaves no partial cache behind. A ``dst`` that exists is kept (its name is
    its source's content digest). ``elsewhere``: the caller's option for moving the cache (full disk message).
    """
    unique = {j[1]: j for j in jobs}  # the same file may be listed by two splits
    jobs = [j for j in unique.values() if not Path(j[1]).is_file()]
    if not jobs:
        return
    cache_dir = Path(cache_dir)
    staging = Path(tempfile.mkdtemp(prefix=TMP_PREFIX, dir=cache_dir))
    try:
        staged = [(src, staging / Path(dst).relative_to(cache_dir), cam, out) for src, dst, cam, out in jobs]
        workers = workers or min(8, os.cpu_count() or 1)
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for f in [pool.submit(process_image, *j, elsewhere) for j in staged]:
                f.result()
        for (_, dst, _, _), (_, tmp, _, _) in zip(jobs, staged):
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp, dst)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def plan_paths(paths: List[Path], root: Path, cache_dir: Path, cam: Intrinsics, downscale: float,
               jobs: List[Tuple[Path, Path, Intrinsics, Intrinsics]]) -> Dict[Path, Path]:
    """Map each source path to the path to read (itself, or its cache copy, queued on ``jobs``). Each source
    is hashed here (once per process while unchanged, :func:`source_digest`): its copy's name holds the digest."""
    if not needs_processing(cam, downscale):
        return {p: p for p in paths}
    out_cam = output_camera(cam, downscale)
    mapping = {}
    for p in paths:
        if not Path(p).is_file():
            raise UserError(f"image {p} does not exist")
        dst = cache_path_for(p, root, cache_dir, cam, downscale, image_key(p))
        jobs.append((p, dst, cam, out_cam))
        mapping[p] = dst
    return mapping
