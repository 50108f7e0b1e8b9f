"""Pinhole cameras with optional lens distortion, pose conventions and rotation helpers.

Pixel convention everywhere in RetinexGS: the centre of pixel (0, 0) is at (0.5, 0.5), as in COLMAP and
instant-ngp. OpenCV puts that centre at (0, 0), so calls into OpenCV shift the principal point by 0.5.

World/camera convention: OpenCV (x right, y down, z forward). Transforms JSON files use the OpenGL/Blender
convention (x right, y up, z back); :func:`opengl_to_opencv` converts a camera-to-world matrix.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, replace
from typing import Sequence, Tuple

import numpy as np

from retinexgs.errors import UserError

# COLMAP model name -> names of its parameters, in COLMAP's order.
COLMAP_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsics of one image as the scene's files declare them: size, pinhole parameters and OpenCV distortion
    coefficients (width and height first). The renderer's camera, with its pose, is :class:`retinexgs.render.Camera`.

    ``dist`` holds OpenCV's coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]); empty or all zero means
    an undistorted pinhole camera.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: Tuple[float, ...] = ()

    @property
    def is_distorted(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return any(float(c) != 0.0 for c in self.dist)

    def K(self) -> np.ndarray:
        """3x3 intrinsics matrix in the pixel-centre convention (centre of pixel (0,0) at (0.5, 0.5))."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def K_opencv(self) -> np.ndarray:
        """3x3 intrinsics matrix in OpenCV's convention (centre of pixel (0,0) at (0, 0))."""
        K = self.K()
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        return K

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera for an image resized to ``width`` x ``height`` (distortion is scale-free)."""
        sx, sy = width / self.width, height / self.height
        return replace(self, width=int(width), height=int(height), fx=self.fx * sx, fy=self.fy * sy,
                       cx=self.cx * sx, cy=self.cy * sy)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Project [N,3] camera-space points (OpenCV axes) to [N,2] pixel positions, distortion included."""
        p = np.asarray(points_cam, dtype=np.float64)
        x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
        x, y = distort_normalized(x, y, self.dist)
        return np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=-1)

    def key(self) -> str:
        """A short stable hash of the intrinsics, used to name cache folders."""
        text = repr((self.width, self.height, self.fx, self.fy, self.cx, self.cy, tuple(self.dist)))
        return hashlib.sha1(text.encode()).hexdigest()[:10]


# How far R Rᵀ may stray from the identity: generous for poses written with a few decimals, tight
# enough to refuse a scaled, sheared or degenerate matrix.
ROTATION_TOLERANCE = 1e-2


def check_rotation(R: np.ndarray, where: str, field: str = "rotation") -> None:
    """UserError naming ``where`` and ``field`` unless ``R`` is a finite proper rotation (within tolerance).

    An all-zero, rank-deficient, scaled, sheared or mirrored 3x3 block would train silently into garbage.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise UserError(f"{where}: {field} is not a finite 3x3 rotation")
    rank = int(np.linalg.matrix_rank(R, tol=1e-6))
    if rank < 3:
        raise UserError(f"{where}: {field} is {'all zero' if rank == 0 else f'rank-deficient (rank {rank})'}; "
                        "a camera pose needs a rotation matrix (orthonormal, determinant 1)")
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > ROTATION_TOLERANCE or det < 0:
        raise UserError(f"{where}: {field} is not a rotation (max |R Rᵀ - I| = {err:.3g}, det = {det:.3g}); "
                        "a camera pose needs an orthonormal matrix with determinant 1, without scale")


def check_camera(cam: "Intrinsics", where: str) -> None:
    """UserError naming ``where`` and the field unless the intrinsics are usable (positive size and focal
    lengths, finite principal point and distortion)."""
    for name in ("width", "height"):
        if not int(getattr(cam, name)) > 0:
            raise UserError(f"{where}: image {name} must be a positive number of pixels, got {getattr(cam, name)}")
    for name, label in (("fx", "focal length fx (fl_x)"), ("fy", "focal length fy (fl_y)")):
        value = float(getattr(cam, name))
        if not (math.isfinite(value) and value > 0):
            raise UserError(f"{where}: {label} must be a positive number, got {value}")
    for name in ("cx", "cy"):
        value = float(getattr(cam, name))
        if not math.isfinite(value):
            raise UserError(f"{where}: principal point {name} must be a finite number, got {value}")
    if not all(math.isfinite(float(c)) for c in cam.dist):
        raise UserError(f"{where}: distortion coefficients must be finite numbers, got {tuple(cam.dist)}")


def distort_normalized(x: np.ndarray, y: np.ndarray, dist: Sequence[float]) -> Tuple[np.ndarray, np.ndarray]:
    """Apply OpenCV's distortion model (up to 8 coefficients) to normalised image coordinates."""
    c = list(dist) + [0.0] * (8 - len(dist))
    k1, k2, p1, p2, k3, k4, k5, k6 = (float(v) for v in c[:8])
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def camera_from_colmap(model: str, width: int, height: int, params: Sequence[float], where: str = "") -> Intrinsics:
    """Build the :class:`Intrinsics` from a COLMAP camera model name and its parameter list."""
    model = str(model).upper()
    if model not in COLMAP_MODELS:
        raise UserError(f"{where or 'COLMAP model'}: camera model {model} is not supported; "
                        f"supported models: {', '.join(COLMAP_MODELS)}")
    names = COLMAP_MODELS[model]
    if len(params) != len(names):
        raise UserError(f"{where or 'COLMAP model'}: camera model {model} needs {len(names)} parameters, "
                        f"got {len(params)}")
    p = dict(zip(names, (float(v) for v in params)))
    fx = p.get("fx", p.get("f"))
    fy = p.get("fy", p.get("f"))
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        dist: Tuple[float, ...] = ()
    elif model == "SIMPLE_RADIAL":
        dist = (p["k"], 0.0, 0.0, 0.0)
    elif model == "RADIAL":
        dist = (p["k1"], p["k2"], 0.0, 0.0)
    elif model == "OPENCV":
        dist = (p["k1"], p["k2"], p["p1"], p["p2"])
    else:  # FULL_OPENCV: OpenCV orders k3 after the tangential terms, as COLMAP does
        dist = tuple(p[n] for n in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"))
    cam = Intrinsics(int(width), int(height), float(fx), float(fy), p["cx"], p["cy"], dist)
    check_camera(cam, where or "COLMAP model")
    return cam


def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """Convert a camera-to-world matrix from OpenGL axes (y up, z back) to OpenCV axes (y down, z forward)."""
    out = np.array(c2w, dtype=np.float64, copy=True)
    out[:3, 1:3] *= -1.0
    return out


def qvec_to_rotmat(q: Sequence[float]) -> np.ndarray:
    """Rotation matrix of a unit quaternion given as (w, x, y, z), COLMAP's order."""
    w, x, y, z = (float(v) for v in q)
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) with w >= 0 of a rotation matrix (numerically stable branch choice)."""
    R = np.asarray(R, dtype=np.float64)
    # Eigenvector of the symmetric 4x4 matrix built from R (robust for any rotation angle).
    Rxx, Ryx, Rzx, Rxy, Ryy, Rzy, Rxz, Ryz, Rzz = R.flat
    K = np.array([
        [Rxx - Ryy - Rzz, 0, 0, 0],
        [Ryx + Rxy, Ryy - Rxx - Rzz, 0, 0],
        [Rzx + Rxz, Rzy + Ryz, Rzz - Rxx - Ryy, 0],
        [Ryz - Rzy, Rzx - Rxz, Rxy - Ryx, Rxx + Ryy + Rzz],
    ]) / 3.0
    vals, vecs = np.linalg.eigh(K)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return -q if q[0] < 0 else q


def c2w_from_w2c(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 camera-to-world matrix from a world-to-camera rotation and translation."""
    out = np.eye(4)
    out[:3, :3] = np.asarray(R).T
    out[:3, 3] = -np.asarray(R).T @ np.asarray(t)
    return out
