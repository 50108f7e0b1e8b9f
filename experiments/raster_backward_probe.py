"""Probe (issue 65): the render's forward and backward alone, on a trained fox-dark model's views, for an A/B of two
builds of the kernels on one card.

The raster backward is 27 % of a fox-dark step's kernel time at 58k Gaussians (experiments/notes/2026-11-30-
step-bound.md). ``save`` trains a scene for ``--steps`` steps and stores what a training render reads (the
Gaussians, the per-Gaussian channels of each view, the cameras); ``time`` renders those views with the build on
PYTHONPATH and prints the forward and the backward in ms (the GPU drained around each, the median over ``--iters`` passes over the
views) and a checksum of the gradients, so that two builds can be compared on the same inputs. Needs a CUDA GPU.

    python experiments/raster_backward_probe.py save SCENE FILE [--steps 3000] [--views 8]
    python experiments/raster_backward_probe.py time FILE [--iters 30] [--kernels PASSES]
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch


def save(scene_dir: Path, file: Path, steps: int, views: int) -> None:
    from retinexgs.run.config import load_config
    from retinexgs.run.folder import open_scene
    from retinexgs.train.trainer import Trainer

    cfg = load_config([], [])
    scene = open_scene(scene_dir, cfg)
    with tempfile.TemporaryDirectory() as run:
        tr = Trainer(cfg, scene, Path(run), "cuda", progress=False, log=lambda s: None)
        tr.train(stop_after=steps)
        g = tr.model.gaussians
        picked = tr.views[:: max(1, len(tr.views) // views)][:views]
        with torch.no_grad():
            data = {
                "means": g.means.detach().clone(), "quats": g.quats.detach().clone(),
                "scales": g.scales.detach().clone(), "opacities": g.opacities.detach().clone(),
                "cameras": [tv.camera for tv in picked],
                "colors": [tr.model.channels(tv.center, tr.active_degree(steps)).detach().clone() for tv in picked],
                "depth": bool(tr.depth_prior),
            }
    torch.save(data, file)
    print(f"saved {len(g)} Gaussians and {len(picked)} views after {steps} steps to {file}")


def _now(device: str) -> float:
    """Milliseconds since an arbitrary origin, with the GPU drained (the probe times whole kernels' spans)."""
    if device == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() * 1e3


def time_views(file: Path, iters: int, device: str = "cuda", kernels: int = 0) -> None:
    from retinexgs.render import rasterize_gaussians

    data = torch.load(file, weights_only=False)
    base = [data[k].to(device) for k in ("means", "quats", "scales", "opacities")]
    fwd, bwd, check = [], [], 0.0
    gen = torch.Generator(device=device).manual_seed(0)
    for it in range(iters + 2):
        tf = tb = 0.0
        for cam, colors in zip(data["cameras"], data["colors"]):
            args = [t.detach().requires_grad_() for t in base + [colors.to(device)]]
            t0 = _now(device)
            out = rasterize_gaussians(*args, cam, validate=False, render_depth=data["depth"])
            t1 = _now(device)
            w = torch.rand(out.image.shape, device=device, generator=gen)
            t2 = _now(device)
            grads = torch.autograd.grad((out.image * w).sum(), args)
            t3 = _now(device)
            tf += t1 - t0
            tb += t3 - t2
            if it == 0:
                check += float(sum(gr.double().abs().sum() for gr in grads))
        if it >= 2:  # two warm-up passes
            fwd.append(tf / len(data["cameras"]))
            bwd.append(tb / len(data["cameras"]))
    n = data["means"].shape[0]
    print(f"{n} Gaussians, {len(data['cameras'])} views, channels {data['colors'][0].shape[1]}"
          f"{' + depth' if data['depth'] else ''}: forward {statistics.median(fwd):.3f} ms, "
          f"backward {statistics.median(bwd):.3f} ms a view (median of {iters}); gradient |sum| {check:.6e}")
    if kernels:
        _kernel_times(base, data, device, kernels)


def _kernel_times(base, data, device: str, passes: int) -> None:
    """The GPU time of each kernel a view's forward + backward launches (torch.profiler, ``passes`` passes over
    the views): the kernels' own time, without the host's share that the spans above include."""
    from torch.profiler import ProfilerActivity, profile

    from retinexgs.render import rasterize_gaussians

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    with profile(activities=acts) as prof:
        for _ in range(passes):
            for cam, colors in zip(data["cameras"], data["colors"]):
                args = [t.detach().requires_grad_() for t in base + [colors.to(device)]]
                out = rasterize_gaussians(*args, cam, validate=False, render_depth=data["depth"])
                torch.autograd.grad(out.image.sum(), args)
    views = passes * len(data["cameras"])
    attr = "device_time_total" if device == "cuda" else "cpu_time_total"
    rows = sorted(prof.key_averages(), key=lambda e: -getattr(e, attr))
    if device == "cuda":
        rows = [e for e in rows if e.device_type.name == "CUDA" or "kernel" in e.key.lower()]
    for e in rows[:8]:
        print(f"  {getattr(e, attr) / views:9.1f} us a view  {e.count // views:3d}x  {e.key[:90]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("save")
    s.add_argument("scene", type=Path)
    s.add_argument("file", type=Path)
    s.add_argument("--steps", type=int, default=3000)
    s.add_argument("--views", type=int, default=8)
    t = sub.add_parser("time")
    t.add_argument("file", type=Path)
    t.add_argument("--iters", type=int, default=30)
    t.add_argument("--device", default="cuda", help="cpu: a smoke run of the probe itself")
    t.add_argument("--kernels", type=int, default=0, metavar="PASSES",
                   help="also each kernel's own GPU time, over PASSES profiled passes")
    args = ap.parse_args()
    if args.cmd == "time" and (args.iters < 1 or args.kernels < 0):
        ap.error("--iters must be at least 1 and --kernels at least 0")
    if args.cmd == "save":
        save(args.scene, args.file, args.steps, args.views)
    else:
        time_views(args.file, args.iters, args.device, args.kernels)


if __name__ == "__main__":
    main()
