"""COLMAP sparse models: finding them, reading them with pycolmap (binary or text, with or without the
rigs/frames files of newer COLMAP versions), and turning one into views.

The COLMAP reader looks for images next to the model: the folder given, else ``<scene>/images``, else
``<scene>/low`` (LOM layout), else the scene folder itself; the first folder holding every registered
image's file wins. When that folder is ``low/`` and a sibling ``high/`` exists, views are paired with it (a
camera raw file by stem: ``low/X.dng`` with ``high/X.png``). Images named ``X.dng`` are read as raw views; a
model naming the camera's ``X.jpg`` reads the JPEGs, even with ``X.dng`` beside them (only a bare folder of
RAW + JPEG pairs, through SfM, trains on the raw files: docs/raw.md).
Views are split into train/test by ``<scene>/split.json`` ({"train": [...], "test": [...]}) when present,
else every ``test_every``-th view (sorted by name) is a test view, else all views are train views.
"""
from __future__ import annotations

import json
import math
import mmap
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from retinexgs.data.camera import Intrinsics, c2w_from_w2c, camera_from_colmap, check_rotation
from retinexgs.data.declared import DeclaredScene, DeclaredView
from retinexgs.errors import UserError
from retinexgs.data.pairing import check_same_files, high_partner

# Where load_scene looks for a model inside a scene folder, in order.
MODEL_SUBDIRS = (".", "sparse/0", "sparse", "colmap_sparse/0", "colmap_sparse", "colmap/sparse/0")


@dataclass
class ColmapImage:
    """A registered image: file name, camera id and camera-to-world (OpenCV axes)."""

    name: str
    camera_id: int
    c2w: np.ndarray


@dataclass
class ColmapModel:
    """The parts of a COLMAP reconstruction RetinexGS uses."""

    path: Path
    cameras: Dict[int, Intrinsics]
    images: Dict[int, ColmapImage]  # registered images only
    points: np.ndarray  # [P,3] float64
    colors: np.ndarray  # [P,3] uint8


def model_format(model_dir: Path) -> str:
    """'bin' or 'txt' depending on which cameras file the folder holds ('' when neither)."""
    if (Path(model_dir) / "cameras.bin").is_file():
        return "bin"
    if (Path(model_dir) / "cameras.txt").is_file():
        return "txt"
    return ""


# The three files of a COLMAP model, per format; rigs/frames (COLMAP >= 3.12) are optional.
MODEL_FILES = {"bin": ("cameras.bin", "images.bin", "points3D.bin"),
               "txt": ("cameras.txt", "images.txt", "points3D.txt")}


def find_model_dir(path: Path) -> Optional[Path]:
    """The first folder under ``path`` (see MODEL_SUBDIRS) holding cameras.bin or cameras.txt.

    UserError for a folder on that list holding part of a model without its cameras file (e.g. only
    points3D.bin, a half copy): taken for "no model", the scene went to SfM, which wrote into the scene folder
    for a minute; the files missing are named instead."""
    for sub in MODEL_SUBDIRS:
        d = (Path(path) / sub)
        if model_format(d):
            return d
        for fmt, names in MODEL_FILES.items():
            present = [n for n in names if (d / n).is_file()]
            if present:
                missing = [n for n in names if n not in present]
                raise UserError(f"COLMAP model {d} is incomplete: it holds {', '.join(present)} but not "
                                f"{', '.join(missing)}; copy the whole model (cameras, images and points3D) "
                                f"or remove the folder")
    return None


# ---- structure checks of the model files, before pycolmap reads them ----------------------------------------
# pycolmap trusts the counts in a binary model: a 2-byte points3D.bin made it reserve gigabytes and die with
# std::bad_alloc, a half cameras.bin gave junk distortion. A pure-Python walk of COLMAP's layout (little endian)
# costs well under a second for a million points and names the broken file instead.

# Parameters per COLMAP camera model id (COLMAP's src/colmap/sensor/models.h).
COLMAP_MODEL_NUM_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16, 12: 4,
                           13: 5, 14: 3, 15: 4, 16: 6, 17: 2}
# Parameters per model name, for the text format (names as COLMAP writes them).
COLMAP_MODEL_PARAMS_BY_NAME = {
    "SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "OPENCV_FISHEYE": 8,
    "FULL_OPENCV": 12, "FOV": 5, "SIMPLE_RADIAL_FISHEYE": 4, "RADIAL_FISHEYE": 5, "THIN_PRISM_FISHEYE": 12,
    "RAD_TAN_THIN_PRISM_FISHEYE": 16, "SIMPLE_DIVISION": 4, "DIVISION": 5, "SIMPLE_FISHEYE": 3, "FISHEYE": 4,
    "EUCM": 6, "EQUIRECTANGULAR": 2}


class _Corrupt(Exception):
    """A model file that does not follow COLMAP's layout; the message says where it breaks."""


class _Walker:
    """Reads little-endian fields from a buffer, raising :class:`_Corrupt` past its end."""

    def __init__(self, buf, what: str):
        self.buf, self.pos, self.size, self.what = buf, 0, len(buf), what

    def take(self, fmt: str, where: str):
        n = struct.calcsize(fmt)
        if self.pos + n > self.size:
            raise _Corrupt(f"ends in the middle of {where}")
        out = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += n
        return out

    def skip(self, n: int, where: str) -> None:
        if n < 0 or self.pos + n > self.size:
            raise _Corrupt(f"ends in the middle of {where}")
        self.pos += n

    def count(self, noun: str, min_record: int) -> int:
        if self.size < 8:
            raise _Corrupt(f"{self.size} bytes, too short to hold the number of {noun}")
        (n,) = self.take("<Q", "the count")
        if n * min_record > self.size - 8:  # a count the file cannot hold: refuse before walking it
            raise _Corrupt(f"says {n} {noun} but its {self.size} bytes hold at most "
                           f"{(self.size - 8) // min_record}")
        return n

    def done(self, n: int, noun: str) -> None:
        if self.pos != self.size:
            raise _Corrupt(f"{self.size - self.pos} unexpected bytes after the last of {n} {noun}")


def _walk_cameras(w: _Walker) -> None:
    n = w.count("cameras", 24)
    for i in range(n):
        where = f"camera {i + 1} of {n}"
        _cid, model, width, height = w.take("<iiQQ", where)
        if model not in COLMAP_MODEL_NUM_PARAMS:
            raise _Corrupt(f"{where} has unknown camera model id {model}")
        if not (0 < width < 1 << 20 and 0 < height < 1 << 20):
            raise _Corrupt(f"{where} is {width}x{height} pixels")
        params = w.take(f"<{COLMAP_MODEL_NUM_PARAMS[model]}d", where)
        if not all(math.isfinite(p) for p in params):
            raise _Corrupt(f"{where} has parameters that are not finite numbers")
    w.done(n, "cameras")


def _walk_images(w: _Walker) -> None:
    n = w.count("images", 4 + 56 + 4 + 1 + 8)
    for i in range(n):
        where = f"image {i + 1} of {n}"
        w.skip(64, where)  # id, quaternion, translation, camera id
        end = w.buf.find(b"\0", w.pos)
        if end < 0:
            raise _Corrupt(f"ends in the middle of {where}'s file name")
        w.pos = end + 1
        (n2d,) = w.take("<Q", where)
        if n2d > (w.size - w.pos) // 24:
            raise _Corrupt(f"{where} lists {n2d} 2D points but the file ends before them")
        w.skip(24 * n2d, where)
    w.done(n, "images")


def _walk_points(w: _Walker) -> None:
    n = w.count("points", 8 + 24 + 3 + 8 + 8)
    for i in range(n):
        where = f"point {i + 1} of {n}"
        w.skip(43, where)  # id, xyz, rgb, error
        (track,) = w.take("<Q", where)
        if track > (w.size - w.pos) // 8:
            raise _Corrupt(f"{where} has a track of {track} observations but the file ends before them")
        w.skip(8 * track, where)
    w.done(n, "points")


def _walk_rigs(w: _Walker) -> None:
    n = w.count("rigs", 8)
    for i in range(n):
        where = f"rig {i + 1} of {n}"
        _rid, sensors = w.take("<II", where)
        if sensors > 0:
            w.skip(8, where)  # reference sensor: type, id
        for _ in range(max(0, sensors - 1)):
            _type, _sid, has_pose = w.take("<iIB", where)
            if has_pose:
                w.skip(56, where)
    w.done(n, "rigs")


def _walk_frames(w: _Walker) -> None:
    n = w.count("frames", 4 + 4 + 56 + 4)
    for i in range(n):
        where = f"frame {i + 1} of {n}"
        w.skip(64, where)  # id, rig id, rig-from-world pose
        (ndata,) = w.take("<I", where)
        w.skip(16 * ndata, where)
    w.done(n, "frames")


_BINARY_WALKS = (("cameras.bin", _walk_cameras), ("images.bin", _walk_images), ("points3D.bin", _walk_points),
                 ("rigs.bin", _walk_rigs), ("frames.bin", _walk_frames))


def _text_lines(path: Path):
    """(line number, stripped line) of a COLMAP text file, comments included (images.txt needs the blanks)."""
    with open(path, encoding="utf-8", errors="strict") as f:
        for i, line in enumerate(f, 1):
            yield i, line.strip()


def _numbers(fields, where: str, kinds: str) -> None:
    """Each field parses as its kind ('i' integer, 'f' finite-or-not float)."""
    for f, k in zip(fields, kinds):
        try:
            int(f) if k == "i" else float(f)
        except ValueError:
            raise _Corrupt(f"{where}: {f!r} is not a number") from None


def _check_text(path: Path) -> None:
    name = path.name
    lines = list(_text_lines(path))
    if name == "cameras.txt":
        if not any(line and not line.startswith("#") for _, line in lines):
            raise _Corrupt("no camera lines")
        for no, line in lines:
            if not line or line.startswith("#"):
                continue
            f = line.split()
            need = COLMAP_MODEL_PARAMS_BY_NAME.get(f[1].upper() if len(f) > 1 else "")
            if need is None or len(f) != 4 + need:
                raise _Corrupt(f"line {no} is not 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]'")
            _numbers(f[:1] + f[2:4], f"line {no}", "iii")
            _numbers(f[4:], f"line {no}", "f" * need)
    elif name == "images.txt":
        # two lines per image; the second (its 2D points) may be empty, so only lines before the first image
        # may be skipped as blank or comments
        it = iter(lines)
        for no, line in it:
            if not line or line.startswith("#"):
                continue
            f = line.split()
            if len(f) < 10:
                raise _Corrupt(f"line {no} is not 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'")
            _numbers(f[:9], f"line {no}", "ifffffffi")
            pts = next(it, None)
            if pts is not None and len(pts[1].split()) % 3:
                raise _Corrupt(f"line {pts[0]} is not a list of 'X Y POINT3D_ID' triples")
            if pts is not None:
                _numbers(pts[1].split(), f"line {pts[0]}", "ffi" * (len(pts[1].split()) // 3))
    elif name == "points3D.txt":
        for no, line in lines:
            if not line or line.startswith("#"):
                continue
            f = line.split()
            if len(f) < 8 or (len(f) - 8) % 2:
                raise _Corrupt(f"line {no} is not 'POINT3D_ID X Y Z R G B ERROR TRACK[]'")
            _numbers(f, f"line {no}", "ifffiiif" + "ii" * ((len(f) - 8) // 2))


def check_model_files(model_dir: Path) -> None:
    """UserError naming the file when a COLMAP model file is truncated or corrupt (see the comment above):
    binary files are walked record by record (a count the file cannot hold, a file ending mid-record or with
    bytes after the last record); text files must parse."""
    model_dir = Path(model_dir)
    fmt = model_format(model_dir)
    for name, walk in _BINARY_WALKS if fmt == "bin" else ():
        path = model_dir / name
        if not path.is_file():
            continue
        try:
            with open(path, "rb") as f:
                size = os.fstat(f.fileno()).st_size
                buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
                try:
                    walk(_Walker(buf, name))
                finally:
                    if size:
                        buf.close()
        except _Corrupt as exc:
            raise UserError(f"{path} is truncated or corrupt ({exc}): copy it again or re-run retinexgs sfm") \
                from None
        except OSError as exc:
            raise UserError(f"cannot read {path}: {exc.strerror or exc}") from None
    if fmt == "txt":
        for name in ("cameras.txt", "images.txt", "points3D.txt"):
            path = model_dir / name
            if not path.is_file():
                continue
            try:
                _check_text(path)
            except _Corrupt as exc:
                raise UserError(f"{path} is truncated or corrupt ({exc}): copy it again or re-run retinexgs sfm") \
                    from None
            except UnicodeDecodeError:
                raise UserError(f"{path} is not a COLMAP text file (not UTF-8 text): copy it again or re-run "
                                "retinexgs sfm") from None
            except OSError as exc:
                raise UserError(f"cannot read {path}: {exc.strerror or exc}") from None


def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise UserError("reading COLMAP models needs pycolmap (a dependency of retinexgs): "
                        "pip install pycolmap") from None
    keep_python_sigterm()
    return pycolmap


def keep_python_sigterm() -> None:
    """Undo glog's failure-signal handler for SIGTERM, which importing pycolmap installs (it would turn
    ``kill PID`` into a stack dump): Python's handler (the CLI's clean stop, or the default) is set again.
    glog keeps its handlers for crashes (SIGSEGV, SIGABRT, ...)."""
    import signal
    import threading
    if threading.current_thread() is threading.main_thread():
        handler = signal.getsignal(signal.SIGTERM)
        if handler is not None:
            signal.signal(signal.SIGTERM, handler)


def read_model(model_dir: Path) -> ColmapModel:
    """Read a COLMAP model folder (binary or text) with pycolmap; UserError naming the folder on failure."""
    model_dir = Path(model_dir)
    fmt = model_format(model_dir)
    if not fmt:
        raise UserError(f"{model_dir} holds no COLMAP model (cameras.bin or cameras.txt)")
    # pycolmap reports a missing file as a C++ check failure; name it ourselves first
    missing = [n for n in (f"images.{fmt}", f"points3D.{fmt}") if not (model_dir / n).is_file()]
    if missing:
        raise UserError(f"COLMAP model {model_dir} is incomplete: missing {', '.join(missing)}")
    check_model_files(model_dir)  # a truncated file would make pycolmap allocate gigabytes or read junk
    pycolmap = _pycolmap()
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises ValueError/RuntimeError for malformed or truncated files
        raise UserError(f"cannot read COLMAP model {model_dir}: {exc}") from None
    where = str(model_dir)
    cameras: Dict[int, Intrinsics] = {}
    images: Dict[int, ColmapImage] = {}
    for cid, c in rec.cameras.items():
        cameras[int(cid)] = camera_from_colmap(c.model.name, c.width, c.height, list(c.params),
                                               f"{where} camera {cid}")
    for iid, im in rec.images.items():
        if not im.has_pose:  # unregistered image
            continue
        m = np.asarray(im.cam_from_world().matrix(), np.float64)
        if not np.all(np.isfinite(m)):
            raise UserError(f"COLMAP model {model_dir} image {im.name}: pose is not finite")
        check_rotation(m[:, :3], f"COLMAP model {model_dir} image {im.name}", "rotation (qvec)")
        images[int(iid)] = ColmapImage(im.name, int(im.camera_id), c2w_from_w2c(m[:, :3], m[:, 3]))
    pts = [rec.points3D[i] for i in sorted(rec.points3D.keys())]  # id order, as in the files
    points = np.asarray([p.xyz for p in pts], np.float64).reshape(-1, 3)
    colors = np.asarray([p.color for p in pts], np.uint8).reshape(-1, 3)
    for im in images.values():
        if im.camera_id not in cameras:
            raise UserError(f"COLMAP model {model_dir}: image {im.name} uses missing camera {im.camera_id}")
    return ColmapModel(model_dir, cameras, images, points, colors)


def similarity_from_centres(src: np.ndarray, dst: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (s, R, t) with dst ≈ s R src + t (Umeyama's closed form)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    var = (a ** 2).sum() / len(src)
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


# Below this many views matched to model images, a similarity between the two frames is not determined
# (3 non-collinear centres fix its 7 degrees of freedom).
MIN_FRAME_MATCHES = 3
# A fit whose camera centres miss their matches by more than this share of the rig's spread (RMS) means the views
# were matched to the wrong images or the two frames are not one reconstruction: points mapped through it would
# land in the wrong place, so random points are used. Frames that are copies of each other fit to ~1e-6.
FRAME_FIT_TOLERANCE = 0.05


def match_views_to_model(model: ColmapModel, views: Sequence[DeclaredView]
                         ) -> Tuple[List[Tuple[ColmapImage, DeclaredView]], List[str]]:
    """(model image, view) pairs, and the stems that could not be matched by stem because they are ambiguous.

    A view matches the model image of its file name, else the one of its stem in any format (a LOM scene's
    ``low/X.png`` or ``low/X.dng`` takes the model's ``X.JPG``: the photos are often converted, the model keeps
    the camera's names). A stem names two model images (``a.JPG`` and ``a.png``) or two of the views' files:
    then only full names match it."""
    by_name: Dict[str, List[ColmapImage]] = {}
    by_stem: Dict[str, List[ColmapImage]] = {}
    for im in model.images.values():
        by_name.setdefault(Path(im.name).name, []).append(im)
        by_stem.setdefault(Path(im.name).stem, []).append(im)
    view_files: Dict[str, set] = {}
    for v in views:
        view_files.setdefault(Path(v.image).stem, set()).add(Path(v.image).name)
    pairs: List[Tuple[ColmapImage, DeclaredView]] = []
    ambiguous: List[str] = []
    for v in views:
        hit = None
        for name in (Path(v.image).name, Path(v.name).name):
            if len(by_name.get(name, [])) == 1:
                hit = by_name[name][0]
                break
        stem = Path(v.image).stem
        if hit is None and stem in by_stem:
            if len(by_stem[stem]) == 1 and len(view_files[stem]) == 1:
                hit = by_stem[stem][0]
            elif stem not in ambiguous:
                ambiguous.append(stem)
        if hit is not None:
            pairs.append((hit, v))
    return pairs, ambiguous


def points_in_frame_of(model: ColmapModel, views: Sequence[DeclaredView]) -> Optional[np.ndarray]:
    """The model's points expressed in the world frame of ``views``, or None (after one ``warning:`` line on
    stderr) when the two frames cannot be related: the caller then starts from random points.

    LOM and instant-ngp JSON poses may be a re-centred/rotated/scaled copy of the COLMAP frame; the similarity
    between matched camera centres (:func:`match_views_to_model`) maps the points across. Fewer than
    ``MIN_FRAME_MATCHES`` matches, or a fit off by more than ``FRAME_FIT_TOLERANCE``, returns None: assuming the
    frames equal put the points elsewhere (733 Gaussians and -4 dB on a LOM scene saved as PNG).
    """
    from retinexgs.data.scene import warn  # lazy: the loaders' warning style (scene imports torch)

    pairs, ambiguous = match_views_to_model(model, views)
    src_a = np.asarray([im.c2w[:3, 3] for im, _ in pairs], np.float64).reshape(-1, 3)
    dst_a = np.asarray([v.c2w[:3, 3] for _, v in pairs], np.float64).reshape(-1, 3)
    if len(pairs) < MIN_FRAME_MATCHES:
        views_shown = ", ".join(sorted({Path(v.image).name for v in views})[:3])
        model_shown = ", ".join(sorted(Path(im.name).name for im in model.images.values())[:3])
        why = (f"; stems {', '.join(ambiguous[:3])} name several files, so only full names match them"
               if ambiguous else "")
        warn(f"the COLMAP model {model.path} names {len(model.images)} images but only {len(pairs)} of the "
             f"{len(views)} views match one by file name or stem (views: {views_shown} ...; model: {model_shown} "
             f"...){why}: its {len(model.points)} points cannot be placed in the views' frame, so training starts "
             f"from random points; rename the model's images to the photos' names to use them")
        return None
    if np.allclose(src_a, dst_a, atol=1e-6 * (1 + np.abs(dst_a).max())):
        return model.points
    s, R, t = similarity_from_centres(src_a, dst_a)
    spread = float(np.sqrt(((dst_a - dst_a.mean(0)) ** 2).sum(1).mean()))
    miss = float(np.sqrt(((s * src_a @ R.T + t - dst_a) ** 2).sum(1).mean()))
    if not (spread > 0 and miss <= FRAME_FIT_TOLERANCE * spread):  # coinciding views fix no frame either
        warn(f"the camera centres of the COLMAP model {model.path} and of the {len(pairs)} views matched to it do "
             f"not agree up to a similarity (off by {miss / max(spread, 1e-300):.0%} of the cameras' spread): the "
             f"views were matched to the wrong images or come from another reconstruction, so its points are not "
             f"used and training starts from random points")
        return None
    return s * model.points @ R.T + t


def read_split(root: Path) -> Optional[Dict[str, List[str]]]:
    """``root/split.json`` as {"train": [...], "test": [...], ...}, or None when absent."""
    path = Path(root) / "split.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise UserError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict) or not all(isinstance(v, list) for v in data.values()):
        raise UserError(f"{path} must map split names to lists of file names")
    return {k: [Path(str(n)).name for n in v] for k, v in data.items()}


def split_views(views: List[DeclaredView], root: Path, test_every: int) -> Tuple[List[DeclaredView], List[DeclaredView]]:
    """Split views into (train, test) by split.json, or every ``test_every``-th view, or all train."""
    views = sorted(views, key=lambda v: v.name)
    split = read_split(root)
    if split is not None and "train" in split:
        train_names, test_names = set(split["train"]), set(split.get("test", []))
        train = [v for v in views if Path(v.name).name in train_names]
        test = [v for v in views if Path(v.name).name in test_names]
        if train:
            return train, test
    if test_every and test_every > 0:
        return ([v for i, v in enumerate(views) if i % test_every != 0],
                [v for i, v in enumerate(views) if i % test_every == 0])
    return views, []


def choose_image_dir(root: Path, names: Sequence[str], given: Optional[Path], where: str) -> Path:
    """The folder holding every file in ``names`` (see the module docstring for the search order)."""
    if given is not None:
        given = Path(given)
        cands = [given if given.is_absolute() else Path(root) / given]
    else:
        cands = [Path(root) / "images", Path(root) / "low", Path(root)]
    best, best_missing = None, None
    for d in cands:
        if not d.is_dir():
            continue
        missing = [n for n in names if not (d / n).is_file()]
        if not missing:
            return d
        if best_missing is None or len(missing) < len(best_missing):
            best, best_missing = d, missing
    if best is None:
        raise UserError(f"no image folder found for COLMAP model {where}: looked in "
                        f"{', '.join(str(c) for c in cands)}; pass the folder with images=...")
    shown = ", ".join(best_missing[:5]) + (" ..." if len(best_missing) > 5 else "")
    raise UserError(f"COLMAP model {where} registers images missing from {best}: {shown}")


def read_colmap_scene(root: Path, model_dir: Optional[Path] = None, images: Optional[Path] = None,
                      test_every: int = 0, reader: str = "colmap") -> DeclaredScene:
    """Read a scene folder with a COLMAP model into a :class:`DeclaredScene`."""

    root = Path(root)
    model_dir = Path(model_dir) if model_dir is not None else find_model_dir(root)
    if model_dir is None:
        raise UserError(f"no COLMAP model (cameras.bin/.txt in {root}, sparse/0, colmap_sparse/0) found")
    model = read_model(model_dir)
    if not model.images:
        raise UserError(f"COLMAP model {model_dir} has no registered images")
    names = [im.name for im in model.images.values()]
    image_dir = choose_image_dir(root, names, images, str(model_dir))
    high = image_dir.parent / "high"
    paired = image_dir.name == "low" and high.is_dir()
    if paired:
        check_same_files(image_dir, high)
    views = []
    for im in model.images.values():
        views.append(DeclaredView(im.name, image_dir / im.name, model.cameras[im.camera_id], im.c2w,
                             high_partner(image_dir / im.name, high) if paired else None))
    train, test = split_views(views, root, test_every)
    return DeclaredScene(root, reader, train, test, [], model.points, model.colors, "colmap")
