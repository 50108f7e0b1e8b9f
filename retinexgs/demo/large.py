"""A large synthetic dark scene (issue 34's scale benchmark): the demo scene of :mod:`retinexgs.demo.synthetic`
(same geometry, textures, shading and sensor model) at any size, e.g. 1000 views at 1920×1080, rendered and
written one view at a time.

Rendering is a torch twin of :func:`retinexgs.demo.synthetic.render_linear` (same rays, hits, textures and
shading; the tests compare it in float64 with the NumPy caster), so it runs on the GPU when there is one:
``device="cuda"`` renders in float32 there, ``device="cpu"`` in float32 on the CPU (small scenes, tests).
Memory is bounded whatever the view count: one view is rendered at a time, one supersample offset at a time,
and at most ``2 × workers`` images wait for the writer threads (PNG/JPEG encoding releases the GIL).

Cameras (:func:`large_cameras`): evenly spread in angle around the scene, heights uniform in 1.0–2.4 and
distances in 2.6–3.8 from its centre, each aimed at a point within 0.25 of the centre, so that views are not all
one circle; every (n/n_test)-th view is a test view.

Files: the demo scene's LOM layout (``low/``, ``high/``, ``transforms_train.json``, ``transforms_test.json``,
``split.json``, ``points3d.npy``, ``colmap_sparse/0``), images as JPEG (quality 95, no chroma subsampling:
``fmt="jpg"``, the default, as a camera writes a large capture) or PNG (``fmt="png"``, zlib level 1), names
``0000.jpg`` (more digits past 10 000 views), and ``scene_params.json`` (:data:`PARAMS_FILE`), written last:
:func:`ensure_large_scene` reuses a folder whose parameters match and regenerates one it made itself otherwise.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple, Union

import numpy as np
import torch
from PIL import Image

from retinexgs.demo.synthetic import (AMBIENT_RGB, BOX, BOX_ID, GROUND, GROUND_HALF, LIGHT_DIR, LIGHT_RGB, MISS,
                                      SCENE_CENTER, SPHERES, DemoCamera, _look_at_gl, _sample_points,
                                      _test_indices, _transforms_json, _write_colmap_text)
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write_text

__all__ = ["large_cameras", "render_linear_torch", "make_large_scene", "ensure_large_scene", "scene_params",
           "default_folder_name", "PARAMS_FILE", "FORMATS"]

PARAMS_FILE = "scene_params.json"
GENERATING = ".generating"  # marker of a folder being written by make_large_scene (removed at the end)
VERSION = 1  # bump when the images for the same parameters change
FORMATS = ("jpg", "png")


# ----------------------------------------------------------------------------------------------------
# Cameras

def large_cameras(n_train: int, n_test: int, width: int, height: int, seed: int = 0,
                  fov_x_deg: float = 60.0) -> List[DemoCamera]:
    """The cameras of a large scene, in file-name order (see the module docstring)."""
    if n_train < 1 or n_test < 0:
        raise ValueError("need n_train >= 1 and n_test >= 0")
    if width < 2 or height < 2:
        raise ValueError("need width, height >= 2")
    n = n_train + n_test
    test = set(_test_indices(n, n_test))
    if len(test) != n_test:
        raise ValueError("n_test too large for the number of views")
    rng = np.random.default_rng([seed, 11])
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    digits = max(4, len(str(n - 1)))
    ext = "jpg"  # renamed by make_large_scene to the chosen format
    cams = []
    for k in range(n):
        a = 2 * math.pi * (k + rng.uniform(-0.5, 0.5)) / n
        h, r = rng.uniform(1.0, 2.4), rng.uniform(2.6, 3.8)
        target = SCENE_CENTER + rng.uniform(-0.25, 0.25, 3) * np.array([1.0, 0.5, 1.0])
        eye = np.array([r * math.sin(a), h, r * math.cos(a)])
        cams.append(DemoCamera(f"{k:0{digits}d}.{ext}", "test" if k in test else "train", width, height,
                               fx, fx, width / 2.0, height / 2.0, _look_at_gl(eye, target)))
    return cams


# ----------------------------------------------------------------------------------------------------
# The torch twin of synthetic.py's ray caster (rays [N,3]; same formulas, same order of tests)

def _vec(x, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, np.float64), dtype=like.dtype, device=like.device)


def _hit_spheres(o: torch.Tensor, d: torch.Tensor, tmin: float = 1e-6) -> Tuple[torch.Tensor, torch.Tensor]:
    inf = torch.full((o.shape[0],), math.inf, dtype=o.dtype, device=o.device)
    t_best, idx = inf.clone(), torch.full((o.shape[0],), -1, dtype=torch.long, device=o.device)
    for s, (c, r, _) in enumerate(SPHERES):
        oc = o - _vec(c, o)
        b = (oc * d).sum(-1)
        disc = b * b - ((oc * oc).sum(-1) - r * r)
        sq = disc.clamp_min(0.0).sqrt()
        t0, t1 = -b - sq, -b + sq
        t = torch.where(t0 > tmin, t0, torch.where(t1 > tmin, t1, inf))
        t = torch.where(disc >= 0, t, inf)
        better = t < t_best
        t_best = torch.where(better, t, t_best)
        idx = torch.where(better, torch.full_like(idx, s), idx)
    return t_best, idx


def _hit_box(o: torch.Tensor, d: torch.Tensor, tmin: float = 1e-6) -> Tuple[torch.Tensor, torch.Tensor]:
    lo, hi = _vec(BOX[0], o), _vec(BOX[1], o)
    inv = 1.0 / torch.where(d == 0, torch.full_like(d, 1e-30), d)
    ta, tb = (lo - o) * inv, (hi - o) * inv
    tnear, tfar = torch.minimum(ta, tb), torch.maximum(ta, tb)
    t0, axis = tnear.max(1)
    t1 = tfar.min(1).values
    hit = (t0 <= t1) & (t0 > tmin)
    return torch.where(hit, t0, torch.full_like(t0, math.inf)), axis


def _hit_ground(o: torch.Tensor, d: torch.Tensor, tmin: float = 1e-6) -> torch.Tensor:
    t = -o[:, 1] / d[:, 1]
    p = o + t[:, None] * d
    ok = (d[:, 1] < 0) & (t > tmin) & (p[:, 0].abs() <= GROUND_HALF) & (p[:, 2].abs() <= GROUND_HALF)
    return torch.where(ok, t, torch.full_like(t, math.inf))


def _cast(o: torch.Tensor, d: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(obj [N], point [N,3], normal [N,3]) as synthetic.cast_rays."""
    ts, si = _hit_spheres(o, d)
    tb, axis = _hit_box(o, d)
    tg = _hit_ground(o, d)
    t = torch.minimum(torch.minimum(ts, tb), tg)
    obj = torch.full_like(si, MISS)
    obj = torch.where(torch.isfinite(tg) & (tg == t), torch.full_like(obj, GROUND), obj)
    obj = torch.where(torch.isfinite(tb) & (tb == t), torch.full_like(obj, BOX_ID), obj)
    obj = torch.where(torch.isfinite(ts) & (ts == t), si + 1, obj)
    p = o + torch.where(torch.isfinite(t), t, torch.zeros_like(t))[:, None] * d
    n = torch.zeros_like(p)
    n[obj == GROUND] = _vec((0.0, 1.0, 0.0), p)
    for s, (c, r, _) in enumerate(SPHERES):
        m = obj == s + 1
        n[m] = (p[m] - _vec(c, p)) / r
    m = obj == BOX_ID
    if bool(m.any()):
        ax = axis[m]
        rows = torch.arange(len(ax), device=p.device)
        nb = torch.zeros((len(ax), 3), dtype=p.dtype, device=p.device)
        nb[rows, ax] = -torch.sign(d[m][rows, ax])
        n[m] = nb
    return obj, p, n


def _albedo(p: torch.Tensor, n: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
    """sRGB albedo as synthetic._albedo."""
    a = torch.zeros_like(p)
    m = obj == GROUND
    if bool(m.any()):
        q = p[m]
        chk = (torch.floor(q[:, 0] / 0.5) + torch.floor(q[:, 2] / 0.5)) % 2
        u = (q[:, 0] / GROUND_HALF + 1) / 2
        base = torch.stack([0.55 + 0.25 * u, 0.5 - 0.1 * u, 0.35 + 0.2 * (1 - u)], -1)
        a[m] = base * (0.6 + 0.4 * chk)[:, None]
    for s, (c, r, tex) in enumerate(SPHERES):
        m = obj == s + 1
        if not bool(m.any()):
            continue
        q = (p[m] - _vec(c, p)) / r
        lon = torch.atan2(q[:, 2], q[:, 0])
        lat = torch.asin(q[:, 1].clamp(-1, 1))
        if tex == "stripes":
            st = (torch.floor(lon / (math.pi / 6)) % 2)[:, None]
            a[m] = st * _vec([0.85, 0.2, 0.15], p) + (1 - st) * _vec([0.95, 0.85, 0.6], p)
        elif tex == "gradient":
            a[m] = (0.25 + 0.6 * (q * 0.5 + 0.5)[:, [1, 2, 0]]).clamp(0, 1)
        else:
            chk = ((torch.floor(lon / (math.pi / 4)) + torch.floor(lat / (math.pi / 6))) % 2)[:, None]
            a[m] = chk * _vec([0.15, 0.45, 0.8], p) + (1 - chk) * _vec([0.9, 0.9, 0.85], p)
    m = obj == BOX_ID
    if bool(m.any()):
        q = p[m]
        grid = (((((q / 0.1) % 1.0) - 0.5).abs() > 0.4) & (n[m].abs() < 0.5)).any(1)
        a[m] = torch.where(grid[:, None], _vec([0.1, 0.15, 0.1], p), _vec([0.3, 0.7, 0.35], p))
    return a


def _srgb_to_linear(c: torch.Tensor) -> torch.Tensor:
    c = c.clamp(0.0, 1.0)
    return torch.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.pow(1.0 / 2.4) - 0.055)


def _rays(cam: DemoCamera, ox: float, oy: float, dtype: torch.dtype, device: torch.device
          ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Origins and unit directions [H*W,3] through (col + ox, row + oy), as DemoCamera.pixel_rays."""
    c2w = torch.as_tensor(cam.c2w_gl, dtype=torch.float64)
    right, up, back = (c2w[:3, k].to(device, dtype) for k in range(3))
    j = torch.arange(cam.width, dtype=dtype, device=device)
    i = torch.arange(cam.height, dtype=dtype, device=device)
    xn = (j[None, :] + ox - cam.cx) / cam.fx
    yn = (i[:, None] + oy - cam.cy) / cam.fy
    d = (-back) + xn[..., None] * right + (-yn[..., None]) * up
    d = (d / d.norm(dim=-1, keepdim=True)).reshape(-1, 3)
    return c2w[:3, 3].to(device, dtype).expand_as(d), d


def render_linear_torch(cam: DemoCamera, supersample: int = 2, device: Union[str, torch.device] = "cpu",
                        dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Normal-light linear radiance [H,W,3] of ``cam`` on ``device``: :func:`synthetic.render_linear`'s image,
    one supersample offset at a time (about 0.5 KB of working memory per pixel in float32)."""
    device = torch.device(device)
    ss = max(1, int(supersample))
    light, light_rgb, ambient = (torch.as_tensor(v, dtype=dtype, device=device)
                                 for v in (LIGHT_DIR, LIGHT_RGB, AMBIENT_RGB))
    sky_rgb = torch.tensor([0.8, 0.9, 1.2], dtype=dtype, device=device)
    total = torch.zeros((cam.height * cam.width, 3), dtype=dtype, device=device)
    for b in range(ss):
        for a in range(ss):
            o, d = _rays(cam, (a + 0.5) / ss, (b + 0.5) / ss, dtype, device)
            obj, p, n = _cast(o, d)
            albedo = _srgb_to_linear(_albedo(p, n, obj))
            lit = obj != MISS
            ndl = (n @ light).clamp_min(0.0)
            vis = torch.ones_like(ndl)
            if bool(lit.any()):
                pl, nl = p[lit], n[lit]
                so = pl + 1e-4 * nl
                sd = light.expand_as(so)
                shadowed = torch.isfinite(_hit_spheres(so, sd)[0]) | torch.isfinite(_hit_box(so, sd)[0])
                vis[lit] = (~shadowed).to(dtype)
            r2 = p[:, 0] ** 2 + p[:, 2] ** 2
            falloff = 0.55 + 0.45 * torch.exp(-r2 / 4.0)
            irr = (ambient[None] + light_rgb[None] * (ndl * vis)[:, None]) * falloff[:, None]
            sky = (0.06 + 0.10 * d[:, 1].clamp(0, 1))[:, None] * sky_rgb
            total += torch.where(lit[:, None], albedo * irr, sky)
    return (total / (ss * ss)).reshape(cam.height, cam.width, 3)


# ----------------------------------------------------------------------------------------------------
# Writing

def scene_params(n_train: int, n_test: int, width: int, height: int, seed: int = 0, fmt: str = "jpg",
                 supersample: int = 2, n_points: int = 20000, device: Union[str, torch.device] = "cpu") -> Dict:
    """What identifies a generated scene: equal dicts, equal files (the noise stream depends on the device
    type, so a scene made on the CPU is not reused for the GPU's parameters)."""
    return {"generator": "retinexgs.demo.large", "version": VERSION, "views": int(n_train),
            "test_views": int(n_test), "width": int(width), "height": int(height), "seed": int(seed),
            "format": fmt, "supersample": int(supersample), "n_points": int(n_points),
            "renderer": f"torch-{torch.device(device).type}-float32"}


def _save(arr: np.ndarray, path: Path, fmt: str) -> int:
    img = Image.fromarray(arr)
    if fmt == "jpg":
        img.save(path, format="JPEG", quality=95, subsampling=0)
    else:
        img.save(path, format="PNG", compress_level=1)
    return path.stat().st_size


def make_large_scene(out_dir: Union[str, Path], n_train: int, n_test: int = 8, width: int = 1920,
                     height: int = 1080, seed: int = 0, fmt: str = "jpg", device: Union[str, torch.device] = "cpu",
                     supersample: int = 2, n_points: int = 20000, dark_level: float = 0.03,
                     dark_jitter: float = 0.1, color_cast: Tuple[float, float, float] = (0.92, 0.97, 1.1),
                     full_well: float = 2000.0, read_noise: float = 3.0, exposure: float = 1.6,
                     workers: Optional[int] = None,
                     progress: Optional[Callable[[int, int, float], None]] = None) -> Dict:
    """Render and write a large dark scene into ``out_dir`` (made if missing; see the module docstring), one view
    at a time. The darkening follows :func:`synthetic.make_demo_scene` (per view k, channel gains, Poisson shot
    noise and Gaussian read noise), drawn per view from (``seed``, view index), so any view can be remade alone.

    ``progress(done, total, seconds)`` is called after each view. Returns a summary: views, seconds,
    views_per_second, bytes (the images on disk), device."""
    if fmt not in FORMATS:
        raise ValueError(f"fmt must be one of {FORMATS}, got {fmt!r}")
    out = Path(out_dir)
    dev = torch.device(device)
    cams = large_cameras(n_train, n_test, width, height, seed)
    for c in cams:
        c.name = f"{Path(c.name).stem}.{fmt}"
    for sub in ("low", "high"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    workers = max(1, workers if workers is not None else min(8, os.cpu_count() or 1))
    gen = torch.Generator(device=dev)
    t0 = time.perf_counter()
    size = 0
    pending: List[Future] = []
    with ThreadPoolExecutor(workers) as pool:
        for k, cam in enumerate(cams):
            with torch.no_grad():
                lin = (render_linear_torch(cam, supersample, dev) * exposure).clamp(0.0, 1.0)
                rng = np.random.default_rng([seed, 2, k])
                kk = dark_level * (1.0 + rng.uniform(-dark_jitter, dark_jitter))
                gains = np.asarray(color_cast) * (1.0 + rng.uniform(-0.03, 0.03, 3))
                gen.manual_seed(int(np.random.default_rng([seed, 4, k]).integers(2**62)))
                electrons = lin * torch.as_tensor(kk * gains * full_well, dtype=lin.dtype, device=dev)
                noisy = torch.poisson(electrons, generator=gen) + read_noise * torch.randn(
                    electrons.shape, generator=gen, dtype=lin.dtype, device=dev)
                images = {"high": _linear_to_srgb(lin), "low": _linear_to_srgb(noisy / full_well)}
                images = {s: (v * 255.0).round().clamp(0, 255).to(torch.uint8).cpu().numpy()
                          for s, v in images.items()}
            for sub, arr in images.items():
                pending.append(pool.submit(_save, arr, out / sub / cam.name, fmt))
            while len(pending) >= 2 * workers:  # bounded: the writer threads keep up or rendering waits
                size += pending.pop(0).result()
            if progress is not None:
                progress(k + 1, len(cams), time.perf_counter() - t0)
        for f in pending:
            size += f.result()
    train = [c for c in cams if c.split == "train"]
    test = [c for c in cams if c.split == "test"]
    (out / "transforms_train.json").write_text(json.dumps(_transforms_json(train, "low"), indent=1))
    if test:
        (out / "transforms_test.json").write_text(json.dumps(_transforms_json(test, "high"), indent=1))
    (out / "split.json").write_text(json.dumps({"train": [c.name for c in train], "test": [c.name for c in test]}))
    pts = _sample_points(n_points, np.random.default_rng([seed, 3]))
    np.save(out / "points3d.npy", pts.astype(np.float32))
    _write_colmap_text(out / "colmap_sparse" / "0", cams, pts)
    seconds = time.perf_counter() - t0
    return {"views": len(cams), "seconds": round(seconds, 2), "views_per_second": round(len(cams) / seconds, 3),
            "bytes": size, "device": str(dev), "workers": workers}


def ensure_large_scene(folder: Union[str, Path], params: Dict,
                       progress: Optional[Callable[[int, int, float], None]] = None) -> Tuple[Path, Optional[Dict]]:
    """The scene of ``params`` (:func:`scene_params`) in ``folder``: reused when its :data:`PARAMS_FILE` holds the
    same parameters (returns ``(folder, None)``), else generated (``(folder, summary)``). A folder made by an
    earlier, different or interrupted generation is replaced (its decomposition cache with it); any other
    non-empty folder is refused (UserError), so nothing of the user's is deleted."""
    folder = Path(folder)
    recorded = folder / PARAMS_FILE
    if recorded.is_file():
        try:
            if json.loads(recorded.read_text()).get("params") == params:
                return folder, None
        except ValueError:
            pass
    elif folder.is_dir() and any(folder.iterdir()) and not (folder / GENERATING).exists():
        raise UserError(f"{folder} exists and is not a scene generated by the scale benchmark (no {PARAMS_FILE}); "
                        "choose another folder, or pass it as --scene to train on it as it is")
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    (folder / GENERATING).write_text("being written by retinexgs.demo.large; deleted when complete\n")
    summary = make_large_scene(folder, params["views"], params["test_views"], params["width"], params["height"],
                               params["seed"], params["format"], params["renderer"].split("-")[1],
                               params["supersample"], params["n_points"], progress=progress)
    atomic_write_text(recorded, json.dumps({"params": params, "generation": summary}, indent=2) + "\n")
    (folder / GENERATING).unlink()
    return folder, summary


def default_folder_name(params: Dict) -> str:
    """A folder name that tells the parameters apart: ``dark-1000v8t-1920x1080-jpg-seed0``."""
    return (f"dark-{params['views']}v{params['test_views']}t-{params['width']}x{params['height']}-"
            f"{params['format']}-seed{params['seed']}")

