"""Rasterizer benchmark: ours against the pure-torch reference (CPU) or gsplat (CUDA), side by side.

    python -m retinexgs.bench raster --device cpu
    python -m retinexgs.bench raster --device cuda --vs gsplat

Each case renders SH-degree-3 colours of a random scene (see :mod:`retinexgs.demo.splats`) and reports the
median forward and forward+backward wall time in ms over ``--repeats`` runs after a warm-up.
"""
from __future__ import annotations

import argparse
import statistics
import time
from typing import Callable, Dict, List, Optional, Tuple

import torch

from retinexgs.demo.splats import orbit_camera, random_scene
from retinexgs.render import Camera, get_num_threads, set_num_threads
from retinexgs.render.reference import rasterize_gaussians_reference, spherical_harmonics_reference
from retinexgs.bench.raster_ours import render_ours
from retinexgs.bench.raster_cuda import run_cuda

RenderFn = Callable[[Dict[str, torch.Tensor], Camera, int], torch.Tensor]


def render_reference(scene: Dict[str, torch.Tensor], cam: Camera, degree: int) -> torch.Tensor:
    dirs = scene["means"] - cam.center.to(scene["means"])
    colors = torch.clamp_min(spherical_harmonics_reference(degree, dirs, scene["sh"]) + 0.5, 0.0)
    return rasterize_gaussians_reference(scene["means"], scene["quats"], scene["scales"], scene["opacities"], colors,
                                         cam).image


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_render(fn: RenderFn, scene: Dict[str, torch.Tensor], cam: Camera, degree: int, repeats: int,
                backward: bool, device: str, warmup: int = 1) -> float:
    """Median wall time in ms of one render (and its backward when ``backward``), after ``warmup`` runs."""
    params = {k: v.detach().requires_grad_(backward) for k, v in scene.items()}
    times: List[float] = []
    for i in range(repeats + warmup):
        _sync(device)
        t0 = time.perf_counter()
        image = fn(params, cam, degree)
        if backward:
            image.sum().backward()
        _sync(device)
        if i >= warmup:
            times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def _fmt(ms: Optional[float]) -> str:
    return "—" if ms is None else f"{ms:9.1f}" if ms >= 100 else f"{ms:9.2f}"


def run_cpu(cases: List[Tuple[int, int, int]], repeats: int, reference_max_work: float) -> None:
    """Ours vs the pure-torch reference at each case, then 1 vs 2 threads."""
    threads = get_num_threads()
    print(f"CPU, {threads} OpenMP threads, torch {torch.__version__}, float32, SH degree 3, median of {repeats}")
    print(f"{'gaussians':>9} {'image':>10} | {'ours fwd':>9} {'ours f+b':>9} | {'ref fwd':>9} {'ref f+b':>9} |"
          f" {'speed-up fwd':>12} {'speed-up f+b':>12}")
    for n, w, h in cases:
        scene, cam = random_scene(n), orbit_camera(w, h)
        fwd = time_render(render_ours, scene, cam, 3, repeats, False, "cpu")
        fb = time_render(render_ours, scene, cam, 3, repeats, True, "cpu")
        rf = rb = None
        if n * w * h <= reference_max_work:  # the dense reference is O(pixels x Gaussians)
            # One run each: the dense reference takes minutes here.
            rf = time_render(render_reference, scene, cam, 3, 1, False, "cpu", warmup=0)
            rb = time_render(render_reference, scene, cam, 3, 1, True, "cpu", warmup=0)
        ratio = (lambda a, b: "—" if a is None else f"{a / b:11.0f}x")
        print(f"{n:>9} {f'{w}x{h}':>10} | {_fmt(fwd)} {_fmt(fb)} | {_fmt(rf)} {_fmt(rb)} |"
              f" {ratio(rf, fwd):>12} {ratio(rb, fb):>12}")
    print("\nOpenMP scaling (forward+backward, ms)")
    print(f"{'gaussians':>9} {'image':>10} | {'1 thread':>9} {'2 threads':>9} | {'speed-up':>8}")
    for n, w, h in cases:
        scene, cam = random_scene(n), orbit_camera(w, h)
        res = {}
        for t in (1, 2):
            set_num_threads(t)
            res[t] = time_render(render_ours, scene, cam, 3, repeats, True, "cpu")
        set_num_threads(threads)
        print(f"{n:>9} {f'{w}x{h}':>10} | {_fmt(res[1])} {_fmt(res[2])} | {res[1] / res[2]:7.2f}x")


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m retinexgs.bench raster", description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--vs", default=None, choices=["reference", "gsplat"],
                        help="comparison (default: reference on cpu, gsplat on cuda)")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--quick", action="store_true", help="small cases only (a smoke run)")
    parser.add_argument("--reference-max-work", type=float, default=1e5 * 500 * 375 / 10,
                        help="largest Gaussians x pixels product for which the reference is timed")
    args = parser.parse_args(argv)
    if args.device == "cpu":
        cases = [(10_000, 500, 375), (100_000, 500, 375), (10_000, 1280, 720), (100_000, 1280, 720)]
        if args.quick:
            cases = [(2_000, 160, 120)]
        run_cpu(cases, args.repeats or (3 if args.quick else 7), args.reference_max_work)
        return 0

    return run_cuda(args)


if __name__ == "__main__":
    raise SystemExit(main())
