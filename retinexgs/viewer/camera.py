"""The viewer's camera <-> the renderer's :class:`~retinexgs.render.Camera` (torch only; no viser import).

viser reports a client's camera as ``wxyz`` (the rotation R of ``P_world = R p_camera + t``, a unit
quaternion w, x, y, z), ``position`` (t, the camera centre), the vertical field of view ``fov`` in radians
and the canvas size. Its camera axes are OpenCV's (x right, y down, z forward: viser's ``CameraHandle``
documents look = +z, up = -y), the renderer's convention too, so no axis flip is needed: the
world-to-camera matrix is ``[Rᵀ | -Rᵀ t]``. Both work in the run's normalised world (the frame the
scene's views and the model live in), so the scene normalisation needs no undoing here either.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence, Tuple

import torch

from retinexgs.render import Camera

MAX_SIDE = 4096  # a larger frame is refused: it could only come from junk sizes and would exhaust memory


@dataclass(frozen=True)
class ViewerCamera:
    """A camera as the viewer sends it: world-from-camera quaternion ``wxyz``, centre ``position``,
    vertical ``fov`` (radians), and the frame's ``width`` x ``height`` in pixels."""

    wxyz: Tuple[float, float, float, float]
    position: Tuple[float, float, float]
    fov: float
    width: int
    height: int


def quat_to_matrix(wxyz: torch.Tensor) -> torch.Tensor:
    """[3,3] rotation of a (normalised here) quaternion w, x, y, z."""
    w, x, y, z = (wxyz / wxyz.norm()).tolist()
    return torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=torch.float64)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Quaternion w, x, y, z (w >= 0) of a [3,3] rotation; branches on the largest component for accuracy."""
    R = R.double()
    tr = float(R[0, 0] + R[1, 1] + R[2, 2])
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(torch.argmax(torch.diagonal(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + float(R[i, i] - R[j, j] - R[k, k]), 1e-12))
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = torch.tensor([float(v) for v in q], dtype=torch.float64)
    q = q / q.norm()
    return -q if q[0] < 0 else q


def _finite(name: str, values: Sequence[float], n: int) -> torch.Tensor:
    try:
        t = torch.as_tensor([float(v) for v in values], dtype=torch.float64)
    except (TypeError, ValueError):
        raise ValueError(f"viewer camera {name} must be {n} numbers, got {values!r}") from None
    if t.shape != (n,) or not bool(torch.isfinite(t).all()):
        raise ValueError(f"viewer camera {name} must be {n} finite numbers, got {values!r}")
    return t


def viewer_to_camera(cam: ViewerCamera, scale: float = 1.0) -> Camera:
    """The renderer's camera for a viewer camera, its frame resized by ``scale`` (square pixels, centred
    principal point). Junk (non-finite pose, zero quaternion, fov outside (0, π), sizes < 1 or too large)
    raises a ValueError naming the field."""
    q = _finite("wxyz", cam.wxyz, 4)
    t = _finite("position", cam.position, 3)
    if float(q.norm()) < 1e-8:
        raise ValueError(f"viewer camera wxyz must be a non-zero quaternion, got {cam.wxyz!r}")
    fov = float(cam.fov) if isinstance(cam.fov, (int, float)) else float("nan")
    if not 0.0 < fov < math.pi:
        raise ValueError(f"viewer camera fov must be in (0, pi) radians, got {cam.fov!r}")
    if not (isinstance(scale, (int, float)) and 0.0 < scale <= 4.0):
        raise ValueError(f"resolution scale must be in (0, 4], got {scale!r}")
    for name in ("width", "height"):
        v = getattr(cam, name)
        if isinstance(v, bool) or not isinstance(v, int) or not 0 < v <= MAX_SIDE:
            raise ValueError(f"viewer camera {name} must be an integer in [1, {MAX_SIDE}], got {v!r}")
    width, height = max(1, round(cam.width * scale)), max(1, round(cam.height * scale))
    if max(width, height) > MAX_SIDE:
        raise ValueError(f"frame {width}x{height} exceeds {MAX_SIDE} pixels a side; lower the resolution scale")
    R = quat_to_matrix(q)  # world-from-camera
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R.T
    w2c[:3, 3] = -R.T @ t
    f = 0.5 * height / math.tan(0.5 * fov)
    return Camera(w2c, f, f, width / 2.0, height / 2.0, width, height)


def camera_to_viewer(camera: Camera) -> ViewerCamera:
    """The viewer camera of a renderer camera (for snapping to a training view): its pose, vertical fov from
    fy, and its size. Exact for square pixels and a centred principal point (the viewer has no others)."""
    c2w = torch.linalg.inv(camera.viewmat)
    fov = 2.0 * math.atan(0.5 * camera.height / camera.fy)
    return ViewerCamera(tuple(matrix_to_quat(c2w[:3, :3]).tolist()), tuple(c2w[:3, 3].tolist()), fov,
                        camera.width, camera.height)


def average_up(cameras: Sequence[Camera]) -> Tuple[float, float, float]:
    """The scene's up direction: the mean of the cameras' up vectors (-y of the OpenCV camera in world),
    normalised; the first camera's up when the mean cancels out, and viser's default +z with no cameras."""
    ups = [-c.viewmat[1, :3] for c in cameras]  # row 1 of R_w2c = camera y axis in world
    if not ups:
        return (0.0, 0.0, 1.0)
    mean = torch.stack(ups).mean(0)
    if float(mean.norm()) < 1e-6:
        return tuple(ups[0].tolist())
    return tuple((mean / mean.norm()).tolist())
