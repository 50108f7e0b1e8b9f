"""Kernel-level profile of the raster bench's forward (ours with and without input checks, gsplat), per case.

    python scripts/profile_raster.py [--repeats 10]

Prints, per case and renderer, the wall time per forward and the CUDA kernels' total time per forward, largest
first: where the forward ratio against gsplat goes.
"""
from __future__ import annotations

import argparse
import time

import torch
from torch.profiler import ProfilerActivity, profile

from retinexgs.bench.raster import render_ours, render_ours_unchecked
from retinexgs.bench.raster_cuda import CASES, render_gsplat
from retinexgs.bench.scenes import orbit_camera, random_scene


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=10)
    args = ap.parse_args()
    fns = {"ours": render_ours, "unchecked": render_ours_unchecked}
    try:
        import gsplat  # noqa: F401
        fns["gsplat"] = render_gsplat
    except ImportError:
        pass
    for n, w, h in CASES:
        scene, cam = random_scene(n, device="cuda"), orbit_camera(w, h)
        with torch.no_grad():
            for name, fn in fns.items():
                for _ in range(3):
                    fn(scene, cam, 3)
                torch.cuda.synchronize()
                t0 = time.perf_counter()
                for _ in range(args.repeats):
                    fn(scene, cam, 3)
                torch.cuda.synchronize()
                wall = (time.perf_counter() - t0) / args.repeats * 1e3
                with profile(activities=[ProfilerActivity.CUDA]) as prof:
                    for _ in range(args.repeats):
                        fn(scene, cam, 3)
                    torch.cuda.synchronize()
                rows = {}
                for e in prof.key_averages():
                    t = getattr(e, "device_time_total", None) or getattr(e, "cuda_time_total", 0)
                    if t > 0 and e.key and not e.key.startswith("ProfilerStep"):
                        rows[e.key] = (t / args.repeats / 1e3, e.count / args.repeats)
                total = sum(t for t, _ in rows.values())
                print(f"\n== {n} @ {w}x{h} {name}: wall {wall:.3f} ms, kernels {total:.3f} ms")
                for k, (t, c) in sorted(rows.items(), key=lambda kv: -kv[1][0])[:14]:
                    print(f"  {t:7.3f} ms  x{c:4.1f}  {k[:110]}")
        del scene
        torch.cuda.empty_cache()


if __name__ == "__main__":
    main()
