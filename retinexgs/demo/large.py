"""A large synthetic dark scene (issue 34's scale benchmark): the demo scene of :mod:`retinexgs.demo.synthetic`
(same geometry, textures, shading and sensor model) at any size, e.g. 1000 views at 1920×1080, rendered and
written one view at a time.

Rendering is the demo's own ray caster (:mod:`retinexgs.demo.raycast`, torch), so it runs on the GPU when there is
one: ``device="cuda"`` renders in float32 there, ``device="cpu"`` in float32 on the CPU (small scenes, tests).
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

from retinexgs.data.srgb import linear_to_srgb
from retinexgs.demo.raycast import SCENE_CENTER
from retinexgs.demo.raycast import render_linear as render_linear_torch
from retinexgs.demo.synthetic import (DemoCamera, _look_at_gl, _sample_points, _test_indices, _transforms_json,
                                      _write_colmap_text)
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
                images = {"high": linear_to_srgb(lin), "low": linear_to_srgb(noisy / full_well)}
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

