"""GPU half of ``python -m retinexgs.bench raster``: ours against gsplat in one process, on the same scenes.

Both render SH-degree-3 colours (gsplat evaluates SH itself; we call our SH kernel, then the rasterizer) with
near 0.01, background black, classic (non-antialiased) mode, 16x16 tiles. Cases alternate between the two so
that clocks and caches treat them alike. Also checks that the images agree and reports what differs.
"""
from __future__ import annotations

import argparse
import statistics
from typing import Callable, Dict, List, Tuple

import torch

from retinexgs.bench.raster_ours import render_ours, render_ours_unchecked
from retinexgs.demo.splats import orbit_camera, random_scene
from retinexgs.render import Camera

CASES: List[Tuple[int, int, int]] = [(200_000, 600, 400), (1_000_000, 1280, 720), (3_000_000, 1920, 1080)]


def render_gsplat(scene: Dict[str, torch.Tensor], cam: Camera, degree: int) -> torch.Tensor:
    import gsplat

    dev = scene["means"].device
    K = torch.tensor([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], dtype=torch.float32, device=dev)
    colors, _, _ = gsplat.rasterization(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["sh"],
        cam.viewmat.to(device=dev, dtype=torch.float32)[None], K[None], cam.width, cam.height,
        near_plane=cam.near, sh_degree=degree, rasterize_mode="classic")
    return colors[0]


def _time(fn: Callable, scene, cam, backward: bool, repeats: int) -> Tuple[float, float]:
    """(median ms, peak MiB above the inputs) of one render (+ backward)."""
    params = {k: v.detach().requires_grad_(backward) for k, v in scene.items()}
    times = []
    torch.cuda.synchronize()
    base = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    for i in range(repeats + 3):
        start, stop = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        image = fn(params, cam, 3)
        if backward:
            image.sum().backward()
        stop.record()
        torch.cuda.synchronize()
        if i >= 3:
            times.append(start.elapsed_time(stop))
        del image
        for p in params.values():
            p.grad = None
    peak = (torch.cuda.max_memory_allocated() - base) / 2**20
    return statistics.median(times), peak


def agreement(scene, cam) -> str:
    with torch.no_grad():
        a, b = render_ours(scene, cam, 3), render_gsplat(scene, cam, 3)
    diff = (a - b).abs()
    mse = float((diff ** 2).mean())
    psnr = float("inf") if mse == 0 else -10 * torch.log10(torch.tensor(mse)).item()
    return (f"max |ours - gsplat| = {float(diff.max()):.3e}, mean = {float(diff.mean()):.3e}, "
            f"PSNR(ours, gsplat) = {psnr:.1f} dB, pixels differing > 1/255: "
            f"{float((diff.max(-1).values > 1 / 255).float().mean()) * 100:.3f} %")


def run_cuda(args: argparse.Namespace) -> int:
    if not torch.cuda.is_available():
        print("no CUDA device: run with --device cpu")
        return 2
    vs = args.vs or "gsplat"
    repeats = args.repeats or 30
    print(f"GPU {torch.cuda.get_device_name()}, torch {torch.__version__}, float32, SH degree 3, "
          f"median of {repeats} after 3 warm-ups")
    try:
        import gsplat  # noqa: F401
        have_gsplat = vs == "gsplat"
    except ImportError:
        have_gsplat = False
        print("gsplat is not installed: timing ours only")
    cases = CASES[:1] if args.quick else CASES
    rows = []
    for n, w, h in cases:
        scene, cam = random_scene(n, device="cuda"), orbit_camera(w, h)
        if have_gsplat:
            render_gsplat(scene, cam, 3)  # JIT build / warm-up outside the timings
            print(f"agreement at {n} Gaussians {w}x{h}: {agreement(scene, cam)}")
        res = {}
        for backward in (False, True):
            for name, fn in (("ours", render_ours), ("unchecked", render_ours_unchecked), ("gsplat", render_gsplat)):
                if name == "gsplat" and not have_gsplat:
                    continue
                res[(name, backward)] = _time(fn, scene, cam, backward, repeats)
        rows.append((n, w, h, res))
        del scene
        torch.cuda.empty_cache()
    print(f"\n{'gaussians':>9} {'image':>10} | {'ours fwd':>8} {'gsplat fwd':>10} {'ratio':>6} | "
          f"{'ours f+b':>8} {'gsplat f+b':>10} {'ratio':>6} | {'ours MiB':>8} {'gsplat MiB':>10}")
    for n, w, h, res in rows:
        of, ob = res[("ours", False)], res[("ours", True)]
        gf, gb = res.get(("gsplat", False)), res.get(("gsplat", True))
        ratio = (lambda a, b: f"{a[0] / b[0]:6.2f}" if b else "     —")
        fmt = (lambda r: f"{r[0]:8.2f}" if r else "       —")
        print(f"{n:>9} {f'{w}x{h}':>10} | {fmt(of)} {fmt(gf):>10} {ratio(of, gf)} | {fmt(ob)} {fmt(gb):>10} "
              f"{ratio(ob, gb)} | {ob[1]:8.0f} {(f'{gb[1]:10.0f}' if gb else '         —')}")
    # The public call checks its inputs (NaN/inf, one host sync) and gsplat does not; the trainer and the frame
    # renderer skip the checks. The same cases without them:
    print(f"\nwithout our input checks (validate=False):\n{'gaussians':>9} {'image':>10} | {'ours fwd':>8} {'ratio':>6} | "
          f"{'ours f+b':>8} {'ratio':>6}")
    for n, w, h, res in rows:
        uf, ub = res[("unchecked", False)], res[("unchecked", True)]
        gf, gb = res.get(("gsplat", False)), res.get(("gsplat", True))
        ratio = (lambda a, b: f"{a[0] / b[0]:6.2f}" if b else "     —")
        print(f"{n:>9} {f'{w}x{h}':>10} | {uf[0]:8.2f} {ratio(uf, gf)} | {ub[0]:8.2f} {ratio(ub, gb)}")
    return 0
