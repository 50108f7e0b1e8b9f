"""A small synthetic dark multi-view scene, rendered by an analytic ray caster (no Gaussian renderer).

Scene (world units, y up): a 6×6 checkered ground square at y = 0 with a smooth colour gradient, three
textured spheres (stripes, a smooth colour gradient, a latitude/longitude checker) and a box with
gridded faces. Shading, in linear light: a warm directional light with hard shadows from the spheres and
the box, a cool ambient term, and a smooth spatial falloff (brighter near the scene centre) so the
illumination is not constant. Rays that miss everything see a dim sky gradient.

Per view, ``high/NNNN.png`` is the normal-light image (2×2 supersampled, sRGB, 8-bit) and
``low/NNNN.png`` the dark one, made like LOM-style synthetic darkening: in linear light x·k·gain_c
(k ≈ ``dark_level`` ± ``dark_jitter`` per view, channel gains for a slight blue cast), Poisson shot noise
(``full_well`` electrons at 1.0) plus Gaussian read noise (``read_noise`` electrons), sRGB, 8-bit.
The default k = 0.03 makes the low images ~7–8× darker than the high ones in sRGB (mean ratio ≈ 0.13);
k ≈ 0.06–0.1 gives a ratio of only ~0.2–0.3 after the sRGB curve.

Files written to ``out_dir`` (LOM layout, read by ``retinexgs.data.load_scene``):
    low/NNNN.png, high/NNNN.png          every view, identical names
    transforms_train.json                 frames list "low/NNNN.png"
    transforms_test.json                  frames list "high/NNNN.png" (not written when n_test=0)
        keys: camera_angle_x, camera_angle_y, fl_x, fl_y, cx, cy, w, h, frames[{file_path,
        transform_matrix}], transform_matrix = camera-to-world 4×4, OpenGL/Blender axes (x right,
        y up, z backward); cx, cy in the pixel-centre convention (pixel (0,0)'s centre is (0.5, 0.5)).
    split.json                            {"train": [names], "test": [names]}
    points3d.npy                          [P,6] float32: xyz (world) + rgb in [0,1] (surface albedo)
    colmap_sparse/0/{cameras,images,points3D}.txt
                                          the same cameras (PINHOLE) and points as a COLMAP text model,
                                          so the ordinary loader picks up the initial points.

Ground truth for tests: :func:`demo_cameras` rebuilds the cameras of a call with the same arguments,
:meth:`DemoCamera.pixel_rays` gives the caster's rays, :func:`cast_rays` intersects rays with the scene.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Sequence, Tuple, Union

import numpy as np
import torch
from PIL import Image

from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear
from retinexgs.demo import raycast
from retinexgs.demo.raycast import (AMBIENT_RGB, BOX, BOX_ID, GROUND, GROUND_HALF, LIGHT_DIR, LIGHT_RGB,  # noqa: F401
                                    MISS, SCENE_CENTER, SPHERES)

__all__ = ["DemoCamera", "demo_cameras", "cast_rays", "render_linear", "make_demo_scene",
           "srgb_to_linear", "linear_to_srgb", "SCENE_CENTER"]

# ----------------------------------------------------------------------------------------------------
# Cameras

@dataclass
class DemoCamera:
    """A pinhole camera of the demo scene. ``c2w_gl``: camera-to-world 4×4, OpenGL axes (as in the JSON)."""

    name: str
    split: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    c2w_gl: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return self.c2w_gl[:3, 3].copy()

    def pixel_rays(self, offsets: Sequence[Tuple[float, float]] = ((0.5, 0.5),)) -> Tuple[np.ndarray, np.ndarray]:
        """Ray origins and unit directions [S,H,W,3] through pixel (row i, col j) at (j + ox, i + oy)
        (:func:`retinexgs.demo.raycast.rays`). The default offset (0.5, 0.5) is the pixel centre."""
        pairs = [raycast.rays(self, ox, oy, torch.float64, torch.device("cpu")) for ox, oy in offsets]
        o = torch.stack([p[0] for p in pairs]).reshape(len(pairs), self.height, self.width, 3)
        d = torch.stack([p[1] for p in pairs]).reshape(len(pairs), self.height, self.width, 3)
        return o.numpy().copy(), d.numpy()

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points [N,3] -> [N,3] (u, v, depth), pixel-centre convention (pixel (0,0) centre = (0.5,0.5))."""
        R, C = self.c2w_gl[:3, :3], self.c2w_gl[:3, 3]
        pc = (np.asarray(points, np.float64) - C) @ R  # camera coords, GL axes
        z = -pc[:, 2]
        return np.stack([self.fx * pc[:, 0] / z + self.cx, self.cy - self.fy * pc[:, 1] / z, z], axis=-1)


def _look_at_gl(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    fwd = target - eye
    fwd = fwd / np.linalg.norm(fwd)
    right = np.cross(fwd, np.array([0.0, 1.0, 0.0]))
    right = right / np.linalg.norm(right)
    up = np.cross(right, fwd)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, -fwd, eye
    return m


def _test_indices(n_total: int, n_test: int) -> List[int]:
    if n_test <= 0:
        return []
    return sorted({int(round((k + 0.5) * n_total / n_test)) % n_total for k in range(n_test)})


def demo_cameras(n_train: int = 12, n_test: int = 4, width: int = 96, height: int = 72, seed: int = 0,
                 fov_x_deg: float = 60.0, radius: float = 3.2, cam_height: float = 1.6) -> List[DemoCamera]:
    """The cameras :func:`make_demo_scene` uses for the same arguments, in file-name order.

    Views sit evenly on a circle of ``radius`` around the scene centre (heights jittered by ±0.15 and
    angles by ±3° from ``seed``), all looking at :data:`SCENE_CENTER`; every (n/n_test)-th view is a
    test view.
    """
    n = n_train + n_test
    if n_train < 1 or n_test < 0:
        raise ValueError("need n_train >= 1 and n_test >= 0")
    rng = np.random.default_rng([seed, 1])
    test = set(_test_indices(n, n_test))
    if len(test) != n_test:
        raise ValueError("n_test too large for the number of views")
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    cams = []
    for k in range(n):
        a = 2 * math.pi * k / n + math.radians(rng.uniform(-3, 3))
        h = cam_height + rng.uniform(-0.15, 0.15)
        eye = np.array([radius * math.sin(a), h, radius * math.cos(a)])
        cams.append(DemoCamera(f"{k:04d}.png", "test" if k in test else "train", width, height,
                               fx, fx, width / 2.0, height / 2.0, _look_at_gl(eye, SCENE_CENTER)))
    return cams


# ----------------------------------------------------------------------------------------------------
# Ray casting (retinexgs.demo.raycast, in float64 on the CPU here)

def cast_rays(origins: np.ndarray, dirs: np.ndarray) -> Dict[str, np.ndarray]:
    """Intersect rays [...,3] (unit ``dirs``) with the scene.

    Returns a dict of arrays with the rays' leading shape: ``t`` (inf on miss), ``point`` [...,3],
    ``normal`` [...,3], ``obj`` (:data:`MISS` = -1, ground 0, spheres 1..3, box 100) and ``albedo``
    [...,3] (sRGB-encoded texture colour, 0 on miss).
    """
    shape = np.shape(origins)[:-1]
    o = torch.as_tensor(np.asarray(origins, np.float64).reshape(-1, 3))
    d = torch.as_tensor(np.asarray(dirs, np.float64).reshape(-1, 3))
    t, obj, p, n = raycast.cast(o, d)
    out = {"t": t, "point": p, "normal": n, "obj": obj, "albedo": raycast.albedo(p, n, obj)}
    return {k: v.numpy().reshape(shape + tuple(v.shape[1:])) for k, v in out.items()}


def render_linear(cam: DemoCamera, supersample: int = 2) -> np.ndarray:
    """Normal-light linear radiance [H,W,3] of ``cam`` (``supersample``² rays per pixel, box-filtered), float64."""
    return raycast.render_linear(cam, supersample, "cpu", torch.float64).numpy()


# ----------------------------------------------------------------------------------------------------
# Points and files

def _sample_points(n: int, rng: np.random.Generator) -> np.ndarray:
    """[n,6] surface points (xyz, sRGB albedo in [0,1]) on the ground, spheres (above ground) and box."""
    n_ground = n // 2
    g = np.stack([rng.uniform(-GROUND_HALF, GROUND_HALF, 2 * n_ground), np.zeros(2 * n_ground),
                  rng.uniform(-GROUND_HALF, GROUND_HALF, 2 * n_ground)], -1)
    lo, hi = np.asarray(BOX[0]), np.asarray(BOX[1])
    under_box = (g[:, 0] >= lo[0]) & (g[:, 0] <= hi[0]) & (g[:, 2] >= lo[2]) & (g[:, 2] <= hi[2])
    g = g[~under_box][:n_ground]  # hidden under the box: never observed
    pts, normals, objs = [g], [np.tile([0.0, 1.0, 0.0], (n_ground, 1))], [np.full(n_ground, GROUND)]
    rest = n - n_ground
    per = rest // (len(SPHERES) + 1)
    for s, (c, r, _) in enumerate(SPHERES):
        v = rng.normal(size=(4 * per, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        q = np.asarray(c) + r * v
        keep = q[:, 1] > 0.0
        q, v = q[keep][:per], v[keep][:per]
        pts.append(q), normals.append(v), objs.append(np.full(len(q), s + 1))
    nb = n - sum(len(x) for x in pts)
    q = rng.uniform(lo, hi, size=(nb, 3))
    ax = rng.choice([0, 1, 2, 0, 2], size=nb)  # faces: ±x, top, ±z (no bottom)
    side = rng.integers(0, 2, nb)
    side[ax == 1] = 1
    q[np.arange(nb), ax] = np.where(side == 1, hi[ax], lo[ax])
    nrm = np.zeros((nb, 3))
    nrm[np.arange(nb), ax] = np.where(side == 1, 1.0, -1.0)
    pts.append(q), normals.append(nrm), objs.append(np.full(nb, BOX_ID))
    p, nn, o = np.concatenate(pts), np.concatenate(normals), np.concatenate(objs)
    colour = raycast.albedo(torch.as_tensor(p), torch.as_tensor(nn), torch.as_tensor(o)).numpy()
    return np.concatenate([p, colour], 1)


def _rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (w, x, y, z) with w ≥ 0."""
    K = np.array([
        [R[0, 0] - R[1, 1] - R[2, 2], R[1, 0] + R[0, 1], R[2, 0] + R[0, 2], R[2, 1] - R[1, 2]],
        [R[1, 0] + R[0, 1], R[1, 1] - R[0, 0] - R[2, 2], R[2, 1] + R[1, 2], R[0, 2] - R[2, 0]],
        [R[2, 0] + R[0, 2], R[2, 1] + R[1, 2], R[2, 2] - R[0, 0] - R[1, 1], R[1, 0] - R[0, 1]],
        [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
    ]) / 3.0
    w, v = np.linalg.eigh(K)
    q = v[[3, 0, 1, 2], np.argmax(w)]
    return q if q[0] >= 0 else -q


def _write_colmap_text(model_dir: Path, cams: List[DemoCamera], points: np.ndarray) -> None:
    """The cameras (PINHOLE, world-to-camera in OpenCV axes) and points as a COLMAP text model."""
    model_dir.mkdir(parents=True, exist_ok=True)
    c = cams[0]
    (model_dir / "cameras.txt").write_text(
        "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 PINHOLE {c.width} {c.height} {float(c.fx)!r} {float(c.fy)!r} {float(c.cx)!r} {float(c.cy)!r}\n")
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "# POINTS2D[] as (X, Y, POINT3D_ID)"]
    for k, cam in enumerate(cams):
        c2w = cam.c2w_gl.copy()
        c2w[:3, 1:3] *= -1.0  # OpenGL -> OpenCV axes
        R = c2w[:3, :3].T
        t = -R @ c2w[:3, 3]
        vals = " ".join(repr(float(x)) for x in (*_rotmat_to_qvec(R), *t))
        lines += [f"{k + 1} {vals} 1 {cam.name}", ""]
    (model_dir / "images.txt").write_text("\n".join(lines) + "\n")
    rgb = np.clip(np.round(points[:, 3:] * 255), 0, 255).astype(int)
    pl = ["# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    for i, (p, c8) in enumerate(zip(points[:, :3], rgb)):
        x, y, z = (repr(float(v)) for v in p)
        pl.append(f"{i + 1} {x} {y} {z} {int(c8[0])} {int(c8[1])} {int(c8[2])} 0.0")
    (model_dir / "points3D.txt").write_text("\n".join(pl) + "\n")


def _transforms_json(cams: List[DemoCamera], folder: str) -> dict:
    c = cams[0]
    return {
        "camera_angle_x": 2 * math.atan(c.width / (2 * c.fx)),
        "camera_angle_y": 2 * math.atan(c.height / (2 * c.fy)),
        "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height,
        "frames": [{"file_path": f"{folder}/{cam.name}", "transform_matrix": cam.c2w_gl.tolist()}
                   for cam in cams],
    }


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x * 255.0), 0, 255).astype(np.uint8)


def make_demo_scene(out_dir: Union[str, Path], n_train: int = 12, n_test: int = 4, width: int = 96,
                    height: int = 72, seed: int = 0, n_points: int = 4000, dark_level: float = 0.03,
                    dark_jitter: float = 0.1, color_cast: Tuple[float, float, float] = (0.92, 0.97, 1.1),
                    full_well: float = 2000.0, read_noise: float = 3.0, supersample: int = 2,
                    exposure: float = 1.6) -> Path:
    """Render and write a dark multi-view demo scene to ``out_dir`` (see the module docstring).

    Args:
        n_train, n_test: numbers of train and test views (all views get low/ and high/ images).
        width, height: image size in pixels.
        seed: fixes camera jitter, per-view darkening and noise, and the sampled points.
        n_points: number of initial surface points.
        dark_level, dark_jitter: k = dark_level·(1 + U(−dark_jitter, dark_jitter)) per view (linear light).
        color_cast: per-channel gains of the dark images (also jittered ±3 % per view).
        full_well, read_noise: sensor model in electrons (shot noise at full_well for linear 1.0).
        supersample: rays per pixel side for anti-aliasing.
        exposure: linear gain of the normal-light rendering.

    Returns:
        ``Path(out_dir)``. Ground-truth cameras: ``demo_cameras(n_train, n_test, width, height, seed)``.
    """
    out = Path(out_dir)
    (out / "low").mkdir(parents=True, exist_ok=True)
    (out / "high").mkdir(parents=True, exist_ok=True)
    cams = demo_cameras(n_train, n_test, width, height, seed)
    rng = np.random.default_rng([seed, 2])
    for cam in cams:
        lin = np.clip(render_linear(cam, supersample) * exposure, 0.0, 1.0)
        Image.fromarray(_to_u8(linear_to_srgb(lin))).save(out / "high" / cam.name)
        k = dark_level * (1.0 + rng.uniform(-dark_jitter, dark_jitter))
        gains = np.asarray(color_cast) * (1.0 + rng.uniform(-0.03, 0.03, 3))
        electrons = lin * k * gains * full_well
        noisy = rng.poisson(electrons).astype(np.float64) + rng.normal(0.0, read_noise, lin.shape)
        low = linear_to_srgb(np.clip(noisy / full_well, 0.0, 1.0))
        Image.fromarray(_to_u8(low)).save(out / "low" / cam.name)
    train = [c for c in cams if c.split == "train"]
    test = [c for c in cams if c.split == "test"]
    (out / "transforms_train.json").write_text(json.dumps(_transforms_json(train, "low"), indent=2))
    if test:  # n_test=0: no test split (no transforms_test.json), as a scene without one
        (out / "transforms_test.json").write_text(json.dumps(_transforms_json(test, "high"), indent=2))
    (out / "split.json").write_text(json.dumps({"train": [c.name for c in train], "test": [c.name for c in test]},
                                               indent=2))
    pts = _sample_points(n_points, np.random.default_rng([seed, 3]))
    np.save(out / "points3d.npy", pts.astype(np.float32))
    _write_colmap_text(out / "colmap_sparse" / "0", cams, pts)
    return out
