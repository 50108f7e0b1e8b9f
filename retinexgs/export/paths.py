"""Smooth camera paths through a scene's training poses, for videos (all in the scene's normalised frame).

- ``orbit``: a full circle around the scene centre (the point nearest to all training optical axes, or the
  median of the Gaussians when the axes are nearly parallel), in the plane perpendicular to the mean camera
  up vector, at the mean camera height above the centre and the mean horizontal distance from it, starting
  at the first training camera's side and always looking at the centre. The end frame is not repeated, so
  the video loops.
- ``interpolate``: the training cameras in a nearest-neighbour chain (starting at the camera farthest from
  the others' centroid, so shuffled names do not make the path jump), rotations by quaternion slerp and
  centres linearly between consecutive cameras, frames spaced by travelled distance (centre distance plus
  rotation angle times the mean distance to the scene centre), both end cameras included.

Both use the mean training intrinsics (at the most common image size). Frames are image-less
:class:`~retinexgs.data.scene.View` objects named ``00000``, ``00001``, ...
"""
from __future__ import annotations

import math
from collections import Counter
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np
import torch

from retinexgs.data.camera import qvec_to_rotmat, rotmat_to_qvec
from retinexgs.data.scene import View
from retinexgs.export import PATH_KINDS

def mean_intrinsics(views: Sequence[View]) -> Tuple[float, float, float, float, int, int]:
    """(fx, fy, cx, cy, width, height): the most common image size, intrinsics averaged after rescaling each
    view to that size."""
    width, height = Counter((v.width, v.height) for v in views).most_common(1)[0][0]
    sx = [width / v.width for v in views]
    sy = [height / v.height for v in views]
    fx = float(np.mean([v.fx * s for v, s in zip(views, sx)]))
    fy = float(np.mean([v.fy * s for v, s in zip(views, sy)]))
    cx = float(np.mean([v.cx * s for v, s in zip(views, sx)]))
    cy = float(np.mean([v.cy * s for v, s in zip(views, sy)]))
    return fx, fy, cx, cy, int(width), int(height)


def _cross(a, b) -> np.ndarray:
    # np.cross of two 3-vectors, without its ~25 us of axis handling (it dominated a long orbit's building)
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """4x4 camera-to-world (OpenCV axes: x right, y down, z forward) at ``eye`` looking at ``target``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = _cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along the up vector: any right vector will do
        x = _cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x = x / np.linalg.norm(x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, _cross(z, x), z, eye
    return c2w


def scene_center(views: Sequence[View], points: Optional[torch.Tensor] = None) -> np.ndarray:
    """The point nearest (least squares) to every view's optical axis; the median of ``points`` (or the
    origin) when the axes are too close to parallel for that point to be well defined."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for v in views:
        c2w = v.camera_to_world.numpy()
        d = c2w[:3, 2] / np.linalg.norm(c2w[:3, 2])
        P = np.eye(3) - np.outer(d, d)  # projects onto the plane normal to the axis
        A += P
        b += P @ c2w[:3, 3]
    if len(views) >= 2 and np.linalg.eigvalsh(A)[0] > 0.05 * len(views):
        return np.linalg.solve(A, b)
    if points is not None and len(points):
        return points.detach().double().cpu().median(dim=0).values.numpy()
    return np.zeros(3)


def _up(views: Sequence[View]) -> np.ndarray:
    up = -np.mean([v.camera_to_world[:3, 1].numpy() for v in views], axis=0)  # OpenCV y points down
    n = np.linalg.norm(up)
    return up / n if n > 1e-9 else np.array([0.0, -1.0, 0.0])


def _frame(i: int, c2w: np.ndarray, intrinsics: Tuple[float, float, float, float, int, int]) -> View:
    # A View without an image: what the run's render function takes, so paths render like the test views.
    fx, fy, cx, cy, w, h = intrinsics
    return View(f"{i:05d}", Path(), fx, fy, cx, cy, w, h, torch.from_numpy(np.array(c2w, dtype=np.float64)))


def orbit_path(views: Sequence[View], frames: int, points: Optional[torch.Tensor] = None) -> List[View]:
    """``frames`` views on a circle around the scene centre (see the module docstring)."""
    center, up = scene_center(views, points), _up(views)
    offsets = np.stack([v.camera_center.numpy() for v in views]) - center
    heights = offsets @ up
    horizontal = offsets - np.outer(heights, up)
    radius = float(np.linalg.norm(horizontal, axis=1).mean())
    e1 = horizontal[0] / max(np.linalg.norm(horizontal[0]), 1e-12)
    if np.linalg.norm(horizontal[0]) < 1e-9:  # first camera right above the centre: any horizontal axis
        e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 = e1 / np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    radius = radius if radius > 1e-6 else 1.0
    intr = mean_intrinsics(views)
    middle = center + up * heights.mean()
    cams = []
    for i in range(frames):
        theta = 2.0 * math.pi * i / frames
        eye = middle + radius * (math.cos(theta) * e1 + math.sin(theta) * e2)
        cams.append(_frame(i, look_at(eye, center, up), intr))
    return cams


def chain_order(views: Sequence[View]) -> List[int]:
    """View indices in a nearest-neighbour chain by camera centre, from the camera farthest from the centroid."""
    centers = np.stack([v.camera_center.numpy() for v in views])
    order = [int(np.argmax(np.linalg.norm(centers - centers.mean(0), axis=1)))]
    left = set(range(len(views))) - set(order)
    while left:
        last = centers[order[-1]]
        nxt = min(left, key=lambda j: (float(np.linalg.norm(centers[j] - last)), j))
        order.append(nxt)
        left.remove(nxt)
    return order


def slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (w, x, y, z), along the shorter arc."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: linear interpolation is exact enough and avoids dividing by sin(~0)
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    angle = math.acos(min(dot, 1.0))
    return (math.sin((1 - t) * angle) * q0 + math.sin(t * angle) * q1) / math.sin(angle)


def interpolate_path(views: Sequence[View], frames: int, points: Optional[torch.Tensor] = None) -> List[View]:
    """``frames`` views through the training views in chain order (see the module docstring)."""
    intr = mean_intrinsics(views)
    order = chain_order(views)
    c2ws = [views[i].camera_to_world.numpy() for i in order]
    if len(c2ws) == 1:
        return [_frame(i, c2ws[0], intr) for i in range(frames)]
    quats = [rotmat_to_qvec(c[:3, :3]) for c in c2ws]
    centers = [c[:3, 3] for c in c2ws]
    reach = float(np.mean([np.linalg.norm(c - scene_center(views, points)) for c in centers]))
    lengths = []
    for a in range(len(c2ws) - 1):
        angle = 2.0 * math.acos(min(abs(float(np.dot(quats[a], quats[a + 1]))), 1.0))
        lengths.append(float(np.linalg.norm(centers[a + 1] - centers[a])) + angle * reach)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    if cum[-1] <= 0:  # all cameras identical
        cum = np.arange(len(c2ws), dtype=np.float64)
    cams = []
    for i, s in enumerate(np.linspace(0.0, cum[-1], frames) if frames > 1 else [0.0]):
        a = int(min(np.searchsorted(cum, s, side="right") - 1, len(lengths) - 1))
        t = 0.0 if cum[a + 1] == cum[a] else (s - cum[a]) / (cum[a + 1] - cum[a])
        c2w = np.eye(4)
        c2w[:3, :3] = qvec_to_rotmat(slerp(quats[a], quats[a + 1], float(t)))
        c2w[:3, 3] = (1 - t) * centers[a] + t * centers[a + 1]
        cams.append(_frame(i, c2w, intr))
    return cams


def camera_path(kind: str, views: Sequence[View], frames: int,
                points: Optional[torch.Tensor] = None) -> List[View]:
    """``frames`` views of path ``kind`` (``orbit`` or ``interpolate``) through ``views``."""
    if kind == "orbit":
        return orbit_path(views, frames, points)
    if kind == "interpolate":
        return interpolate_path(views, frames, points)
    raise ValueError(f"unknown path kind {kind!r}; choose from {', '.join(PATH_KINDS)}")
