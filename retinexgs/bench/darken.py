"""darken --raw's speed (issue 65): one view through the plain reference pipeline and the fast one (stage times,
ratio, the files checked bit for bit), and optionally a whole scene of --views views through the worker pool.

The input is a synthetic normal-light photo (smooth colour waves and 8-pixel blocks of texture, JPEG at quality 95,
like the demo's large scene) at --width x --height (default 4000x3000, 12 MP), or --photo. The reference is
raw_sim.capture_mosaic_reference and raw_sim.process_reference (the pipeline as first written: whole arrays, the
sRGB curve on every pixel, the demosaic as 3x3 correlations); the fast path is what ``darken --raw`` runs. Both draw
the same view's random stream, so their DNG mosaic and camera JPEG must be equal: the run fails (exit 1) if not.

``--views N`` also times ``darken --raw`` of N views (copies of the photo under N names) with ``--jobs`` workers
(default: one per CPU core), against N times the reference's serial time per view (the old command ran the views
one after another).

    retinexgs bench darken                         # one 12 MP view: reference vs fast
    retinexgs bench darken --views 44              # and the 44-view scene of issue 65, all cores
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from retinexgs.data import raw_sim
from retinexgs.data.images import read_image_float, write_image_atomic
from retinexgs.data.sensor import SensorModel, darken_scene, view_rng


def synthetic_photo(width: int, height: int, seed: int = 1) -> np.ndarray:
    """uint8 [H, W, 3]: a normal-light test photo (colour waves plus 8x8 blocks of noise-like texture)."""
    rng = np.random.default_rng(seed)
    y = np.arange(height, dtype=np.float32)[:, None]
    x = np.arange(width, dtype=np.float32)[None, :]
    img = np.stack([0.5 + 0.4 * np.sin(x / 97 + c) * np.cos(y / 131 - c) for c in range(3)], axis=-1)
    blocks = rng.standard_normal(((height + 7) // 8, (width + 7) // 8, 3)).astype(np.float32)
    img += 0.1 * blocks.repeat(8, 0).repeat(8, 1)[:height, :width]
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def _timed(fn: Callable, *args) -> Tuple[object, float]:
    start = time.perf_counter()
    result = fn(*args)
    return result, time.perf_counter() - start


def one_view(photo: Path, work: Path, model: SensorModel, camera: raw_sim.RawCamera,
             seed: int = 0) -> Tuple[List[Tuple[str, float, float]], bool]:
    """([(stage, reference s, fast s)], whether the two paths wrote the same DNG and JPEG bytes) for one view."""
    black = camera.black_level(model.full_well, model.read_noise)
    name = "low/" + photo.name
    rows: List[Tuple[str, float, float]] = []
    files: Dict[str, List[bytes]] = {}
    for label, capture, isp in (("reference", raw_sim.capture_mosaic_reference, raw_sim.process_reference),
                                ("fast", raw_sim.capture_mosaic, raw_sim.process)):
        rng = view_rng(seed, name)
        k = model.view_exposure(rng)
        times: Dict[str, float] = {}
        srgb, times["read"] = _timed(read_image_float, photo)
        dn, times["capture (linearise, mosaic, noise, quantise)"] = _timed(capture, srgb, model, camera, k, rng)
        dng, jpg = work / f"{label}.dng", work / f"{label}.jpg"
        _, times["DNG write"] = _timed(raw_sim.write_raw_view, dng, dn, camera, model, k)
        rgb, times["camera ISP (demosaic, colour, sRGB curve)"] = _timed(
            lambda: raw_sim.to_uint8(isp(dn, camera, black)))
        _, times["JPEG encode + write"] = _timed(write_image_atomic, jpg, rgb, model.jpeg_quality)
        files[label] = [dng.read_bytes(), jpg.read_bytes()]
        for i, (stage, t) in enumerate(times.items()):
            if label == "reference":
                rows.append((stage, t, 0.0))
            else:
                rows[i] = (stage, rows[i][1], t)
    return rows, files["reference"] == files["fast"]


def main(argv: Optional[List[str]] = None) -> int:
    """``retinexgs bench darken``: see the module docstring; exit 1 when the fast path's files differ."""
    ap = argparse.ArgumentParser(prog="retinexgs bench darken", description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=4000, help="synthetic photo width (default 4000)")
    ap.add_argument("--height", type=int, default=3000, help="synthetic photo height (default 3000)")
    ap.add_argument("--photo", type=Path, default=None, help="a normal-light photo instead of the synthetic one")
    ap.add_argument("--views", type=int, default=0, help="also darken a scene of this many views (default 0: no)")
    ap.add_argument("--jobs", type=int, default=None, help="workers for --views (default: one per CPU core)")
    ap.add_argument("--tmp", type=Path, default=None, help="folder for the temporary files (default: the system's)")
    args = ap.parse_args(argv)
    if args.width < 22 or args.height < 22 or args.views < 0:
        ap.error("--width and --height must be at least 22 (a DNG's least side) and --views at least 0")
    if args.jobs is not None and args.jobs < 1:
        ap.error(f"--jobs must be at least 1 (worker processes), got {args.jobs}")
    if args.photo is not None and not args.photo.is_file():  # before the temporary folder: one line, no traceback
        ap.error(f"--photo {args.photo}: no such file")
    model, camera = SensorModel(), raw_sim.RawCamera()
    work = Path(tempfile.mkdtemp(prefix="bench-darken-", dir=args.tmp))
    try:
        src = work / "src"
        src.mkdir()
        photo = src / "0000.jpg"
        if args.photo is not None:
            shutil.copyfile(args.photo, photo.with_suffix(args.photo.suffix.lower()))
            photo = photo.with_suffix(args.photo.suffix.lower())
        else:
            write_image_atomic(photo, synthetic_photo(args.width, args.height), quality=95)
        h, w = read_image_float(photo).shape[:2]
        rows, same = one_view(photo, work, model, camera)
        print(f"darken --raw, one view of {w}x{h} ({w * h / 1e6:.1f} MP), {os.cpu_count()} CPU cores")
        print(f"  {'stage':<46} {'reference s':>12} {'fast s':>8} {'ratio':>7}")
        for stage, ref, fast in rows:
            print(f"  {stage:<46} {ref:12.2f} {fast:8.2f} {ref / max(fast, 1e-9):6.1f}x")
        ref_total, fast_total = sum(r[1] for r in rows), sum(r[2] for r in rows)
        print(f"  {'per view':<46} {ref_total:12.2f} {fast_total:8.2f} {ref_total / fast_total:6.1f}x")
        print(f"  DNG and JPEG bit-identical: {'yes' if same else 'NO'}")
        if args.views:
            for i in range(1, args.views):
                os.link(photo, src / f"{i:04d}{photo.suffix}")  # the same pixels under another name
            out = work / "out"
            _, t = _timed(lambda: darken_scene(src, out, model, seed=0, progress=False, raw=camera, jobs=args.jobs))
            jobs = args.jobs or os.cpu_count()
            print(f"darken --raw of {args.views} views, --jobs {jobs}: {t:.1f} s ({t / args.views:.2f} s per view); "
                  f"the reference one view after another: {ref_total * args.views:.1f} s (estimated), "
                  f"{ref_total * args.views / t:.1f}x")
        return 0 if same else 1
    finally:
        shutil.rmtree(work, ignore_errors=True)
