"""Smooth camera paths through a scene's training poses, for videos (all in the scene's normalised frame).

- ``orbit``: for a capture that surrounds the scene, the full circle of ``orbit-360``. For a front-facing
  capture (every training camera looks within :data:`FRONT_FACING_DEG` of the cameras' mean viewing direction,
  as in LLFF-style captures and photos taken from one side), an ellipse that stays within the cameras' spread
  instead, so that the frames show what the cameras saw: centred on the mean camera position, in the plane
  perpendicular to the mean viewing direction, its semi-axes along the cameras' mean right and up vectors the
  90th percentile of the camera positions' distance from the centre along them, every frame looking at the
  focus point (the scene centre below, projected onto the mean viewing axis). Starts at the ellipse's right.
  A ring of cameras all looking steeply down at an object also counts as front-facing; its ellipse is then
  about that ring, looking at the object.
- ``orbit-360``: a full circle around the scene centre (the point nearest to all training optical axes, or the
  median of the Gaussians when the axes are nearly parallel), in the plane perpendicular to the mean camera
  up vector, at the mean camera height above the centre and the mean horizontal distance from it, starting
  at the first training camera's side and always looking at the centre. The end frame is not repeated, so
  the video loops.
- ``interpolate``: the training cameras in a nearest-neighbour chain (starting at the camera farthest from
  the others' centroid, so shuffled names do not make the path jump), rotations by quaternion slerp and
  centres linearly between consecutive cameras, frames spaced by travelled distance (centre distance plus
  rotation angle times the mean distance to the scene centre), both end cameras included.

All use the mean training intrinsics (at the most common image size). Frames are image-less
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

# Half-angle of the cone around the mean viewing direction within which every camera of a front-facing capture
# looks. Cameras around an object look from opposite sides (up to 180° apart); LLFF-style captures stay within
# ~30°; 60° keeps a one-sided arc of up to ~120° on the ellipse as well, where a full circle would go behind.
FRONT_FACING_DEG = 60.0


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


def _viewing_directions(views: Sequence[View]) -> np.ndarray:
    d = np.stack([v.camera_to_world[:3, 2].numpy() for v in views])  # OpenCV z: where the camera looks
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def is_front_facing(views: Sequence[View], max_deg: float = FRONT_FACING_DEG) -> bool:
    """True when every view looks within ``max_deg`` of the views' mean viewing direction (one-sided capture)."""
    d = _viewing_directions(views)
    mean = d.mean(0)
    n = float(np.linalg.norm(mean))
    if n < 1e-6:  # opposite directions cancel: cameras all around the scene
        return False
    return bool(np.all(d @ (mean / n) >= math.cos(math.radians(max_deg)) - 1e-12))


def ellipse_path(views: Sequence[View], frames: int, points: Optional[torch.Tensor] = None) -> List[View]:
    """``frames`` views on an ellipse within the cameras' spread, looking at the focus point (module docstring:
    ``orbit`` of a front-facing capture)."""
    d = _viewing_directions(views)
    forward = d.mean(0) / max(float(np.linalg.norm(d.mean(0))), 1e-12)
    centers = np.stack([v.camera_center.numpy() for v in views])
    middle = centers.mean(0)
    # right and up: the cameras' mean axes made perpendicular to the mean viewing direction
    right = np.mean([v.camera_to_world[:3, 0].numpy() for v in views], axis=0)
    right = right - forward * float(right @ forward)
    if np.linalg.norm(right) < 1e-9:
        right = _cross(forward, [0.0, 1.0, 0.0] if abs(forward[1]) < 0.9 else [1.0, 0.0, 0.0])
    right = right / np.linalg.norm(right)
    down = _cross(forward, right)  # OpenCV y: down, so that right, down, forward is right-handed
    offsets = centers - middle
    a = float(np.percentile(np.abs(offsets @ right), 90))
    b = float(np.percentile(np.abs(offsets @ down), 90))
    depth = float((scene_center(views, points) - middle) @ forward)
    if not depth > 1e-6:  # the centre estimate lies behind the cameras: look as far ahead as the spread is wide
        depth = max(a, b, 1.0)
    focus = middle + depth * forward
    intr = mean_intrinsics(views)
    cams = []
    for i in range(frames):
        theta = 2.0 * math.pi * i / frames
        eye = middle + a * math.cos(theta) * right + b * math.sin(theta) * down
        cams.append(_frame(i, look_at(eye, focus, -down), intr))
    return cams


def orbit_path(views: Sequence[View], frames: int, points: Optional[torch.Tensor] = None) -> List[View]:
    """``frames`` views of ``orbit`` (module docstring): the ellipse of a front-facing capture, else the full
    circle of :func:`orbit_360_path`."""
    if is_front_facing(views):
        return ellipse_path(views, frames, points)
    return orbit_360_path(views, frames, points)


def orbit_360_path(views: Sequence[View], frames: int, points: Optional[torch.Tensor] = None) -> List[View]:
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
    """``frames`` views of path ``kind`` (``orbit``, ``orbit-360`` or ``interpolate``) through ``views``."""
    if kind == "orbit":
        return orbit_path(views, frames, points)
    if kind == "orbit-360":
        return orbit_360_path(views, frames, points)
    if kind == "interpolate":
        return interpolate_path(views, frames, points)
    raise ValueError(f"unknown path kind {kind!r}; choose from {', '.join(PATH_KINDS)}")
