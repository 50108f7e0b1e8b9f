"""A small pure-Python reader (and text writer) for COLMAP sparse models: cameras, images, points3D,
in COLMAP's binary (``.bin``) or text (``.txt``) format.

It is the fallback when ``pycolmap`` is not installed. Rig files (rigs.bin, frames.bin) of newer COLMAP
versions are ignored: the per-image pose stored in images.bin/txt is used, which is exact for the usual
one-camera-per-frame models.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Dict, List, Tuple

import numpy as np

from retinexgs.errors import UserError

# COLMAP's numeric model ids and parameter counts (only the ids matter for reading binary files).
MODEL_IDS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MODEL_NAME_TO_ID = {name: i for i, (name, _) in MODEL_IDS.items()}


@dataclass
class RawCamera:
    """A COLMAP camera as stored: model name, size and parameters."""

    camera_id: int
    model: str
    width: int
    height: int
    params: Tuple[float, ...]


@dataclass
class RawImage:
    """A COLMAP image as stored: world-to-camera quaternion (w, x, y, z) and translation."""

    image_id: int
    qvec: Tuple[float, float, float, float]
    tvec: Tuple[float, float, float]
    camera_id: int
    name: str


class _Reader:
    def __init__(self, f: BinaryIO, path: Path):
        self.f, self.path = f, path

    def read(self, fmt: str):
        size = struct.calcsize("<" + fmt)
        data = self.f.read(size)
        if len(data) != size:
            raise UserError(f"COLMAP file {self.path} is truncated")
        return struct.unpack("<" + fmt, data)

    def skip(self, n: int) -> None:
        self.f.seek(n, 1)

    def cstring(self) -> str:
        out = bytearray()
        while True:
            c = self.f.read(1)
            if not c:
                raise UserError(f"COLMAP file {self.path} is truncated")
            if c == b"\0":
                return out.decode("utf-8")
            out += c


def read_cameras_binary(path: Path) -> Dict[int, RawCamera]:
    """Read cameras.bin."""
    cams = {}
    with open(path, "rb") as f:
        r = _Reader(f, path)
        (n,) = r.read("Q")
        for _ in range(n):
            cam_id, model_id, w, h = r.read("iiQQ")
            if model_id not in MODEL_IDS:
                raise UserError(f"{path}: unknown COLMAP camera model id {model_id}")
            name, nparams = MODEL_IDS[model_id]
            cams[cam_id] = RawCamera(cam_id, name, w, h, r.read("d" * nparams))
    return cams


def read_images_binary(path: Path) -> Dict[int, RawImage]:
    """Read images.bin (2D observations are skipped)."""
    images = {}
    with open(path, "rb") as f:
        r = _Reader(f, path)
        (n,) = r.read("Q")
        for _ in range(n):
            vals = r.read("idddddddi")
            name = r.cstring()
            (npts,) = r.read("Q")
            r.skip(npts * 24)
            images[vals[0]] = RawImage(vals[0], tuple(vals[1:5]), tuple(vals[5:8]), vals[8], name)
    return images


def read_points_binary(path: Path) -> Tuple[np.ndarray, np.ndarray]:
    """Read points3D.bin as xyz [P,3] float64 and rgb [P,3] uint8, in point id order."""
    ids, xyz, rgb = [], [], []
    with open(path, "rb") as f:
        r = _Reader(f, path)
        (n,) = r.read("Q")
        for _ in range(n):
            vals = r.read("QdddBBBd")
            ids.append(vals[0])
            xyz.append(vals[1:4])
            rgb.append(vals[4:7])
            (track_len,) = r.read("Q")
            r.skip(track_len * 8)
    return _by_id(ids, xyz, rgb)


def _by_id(ids, xyz, rgb) -> Tuple[np.ndarray, np.ndarray]:
    order = np.argsort(np.asarray(ids, np.int64), kind="stable")
    return (np.asarray(xyz, np.float64).reshape(-1, 3)[order], np.asarray(rgb, np.uint8).reshape(-1, 3)[order])


def _data_lines(path: Path) -> List[str]:
    with open(path, "r", encoding="utf-8") as f:
        return [line.rstrip("\r\n") for line in f if not line.startswith("#")]


def read_cameras_text(path: Path) -> Dict[int, RawCamera]:
    """Read cameras.txt."""
    cams = {}
    for line in _data_lines(path):
        tok = line.split()
        if not tok:
            continue
        try:
            cams[int(tok[0])] = RawCamera(int(tok[0]), tok[1], int(tok[2]), int(tok[3]),
                                          tuple(float(v) for v in tok[4:]))
        except (ValueError, IndexError):
            raise UserError(f"{path}: malformed camera line: {line!r}") from None
    return cams


def read_images_text(path: Path) -> Dict[int, RawImage]:
    """Read images.txt (each image is a header line followed by a possibly empty points line)."""
    lines = _data_lines(path)
    images = {}
    i = 0
    while i < len(lines):
        tok = lines[i].split()
        if not tok:  # blank line where a header is expected
            i += 1
            continue
        if len(tok) < 10:
            raise UserError(f"{path}: malformed image line: {lines[i]!r}")
        try:
            image_id = int(tok[0])
            q = tuple(float(v) for v in tok[1:5])
            t = tuple(float(v) for v in tok[5:8])
            cam_id = int(tok[8])
        except ValueError:
            raise UserError(f"{path}: malformed image line: {lines[i]!r}") from None
        images[image_id] = RawImage(image_id, q, t, cam_id, " ".join(tok[9:]))
        i += 2  # skip the 2D points line
    return images


def read_points_text(path: Path) -> Tuple[np.ndarray, np.ndarray]:
    """Read points3D.txt as xyz [P,3] float64 and rgb [P,3] uint8, in point id order."""
    ids, xyz, rgb = [], [], []
    for line in _data_lines(path):
        tok = line.split()
        if not tok:
            continue
        try:
            p, c = [float(v) for v in tok[1:4]], [int(v) for v in tok[4:7]]
            ids.append(int(tok[0]))
        except (ValueError, IndexError):
            raise UserError(f"{path}: malformed point line: {line!r}") from None
        if len(p) != 3 or len(c) != 3:
            raise UserError(f"{path}: malformed point line: {line!r}")
        xyz.append(p)
        rgb.append(c)
    return _by_id(ids, xyz, rgb)


def model_format(model_dir: Path) -> str:
    """'bin' or 'txt' depending on which cameras file the folder holds ('' when neither)."""
    if (model_dir / "cameras.bin").is_file():
        return "bin"
    if (model_dir / "cameras.txt").is_file():
        return "txt"
    return ""


def read_model_files(model_dir: Path):
    """Read a model folder: (cameras, images, xyz, rgb) using the binary files when present."""
    fmt = model_format(model_dir)
    need = [model_dir / f"{n}.{fmt}" for n in ("cameras", "images", "points3D")]
    missing = [str(p) for p in need if not p.is_file()]
    if not fmt or missing:
        raise UserError(f"COLMAP model {model_dir} is incomplete: missing {', '.join(missing) or 'cameras.bin'}")
    if fmt == "bin":
        return (read_cameras_binary(need[0]), read_images_binary(need[1])) + read_points_binary(need[2])
    return (read_cameras_text(need[0]), read_images_text(need[1])) + read_points_text(need[2])


def write_model_text(model_dir: Path, cameras: Dict[int, RawCamera], images: Dict[int, RawImage],
                     xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Write a model in COLMAP's text format (no 2D observations, points have empty tracks)."""
    model_dir.mkdir(parents=True, exist_ok=True)
    with open(model_dir / "cameras.txt", "w") as f:
        f.write("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        for c in cameras.values():
            f.write(" ".join([str(c.camera_id), c.model, str(c.width), str(c.height)]
                             + [repr(float(p)) for p in c.params]) + "\n")
    with open(model_dir / "images.txt", "w") as f:
        f.write("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n")
        for im in images.values():
            vals = [repr(float(v)) for v in tuple(im.qvec) + tuple(im.tvec)]
            f.write(" ".join([str(im.image_id)] + vals + [str(im.camera_id), im.name]) + "\n\n")
    with open(model_dir / "points3D.txt", "w") as f:
        f.write("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        for i, (p, c) in enumerate(zip(np.asarray(xyz), np.asarray(rgb))):
            x, y, z = (repr(float(v)) for v in p)
            f.write(f"{i + 1} {x} {y} {z} {int(c[0])} {int(c[1])} {int(c[2])} 0.0\n")
