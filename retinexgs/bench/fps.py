"""Frame rate of a trained run: the full enhanced render against the rasterization alone, side by side.

    python -m retinexgs.bench fps --run RUN [--width W --height H] [--frames 100] [--device cuda] [--vs gsplat]
                                  [--white-balance FORM]

"full" is what ``model.render`` (the training path, torch ops) pays per frame: SH colours + the illumination MLP on
every Gaussian, one 6-channel rasterization, the EnhancementNet and R̂·L̂^g. "full (fused)" is the same frame
through the :class:`~retinexgs.model.inference.InferenceRenderer` that ``render``, ``export`` and the viewer use
(one fused colour kernel, the enhancement as a CUDA graph). "raster" renders the same Gaussians with those 6
channels precomputed, so the difference is the MLP/network share. "fused, serial" (CUDA) is "full (fused)" with
its colour kernel launched after the binning instead of on a side stream beside projection and binning; "fused,
tile cull" with tile culling in the binning (the same pixels, another split of the work; the renderer's default
on CUDA is without). On CUDA the kernel launches per frame of each full stage are counted with torch.profiler
(cudaLaunchKernel and friends; a CUDA graph counts once). Cameras are the run's test views (train views when it
has none), cycled; ``--width/--height`` resize them (intrinsics scaled per axis). ``--white-balance FORM`` adds
"fused + balance": the fused frame with that render-time white balance (``render --white-balance``; issue 53's
target: at most 5 % slower than "full (fused)"): the same renderer call with the balance, which tone ``exposure``
applies inside its one kernel (other tones: the light balanced and encoded again in torch, as ``render`` does).
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional

import torch

from retinexgs.render import Camera, rasterize_gaussians
from retinexgs.model.inference import InferenceRenderer
from retinexgs.errors import UserError
from retinexgs.run.folder import load_run
from retinexgs.model.white_balance import describe_balance, parse_white_balance
from retinexgs.run.render import active_sh_degree, render_function, view_camera, white_balance_of

STAGES = ("full", "full (fused)", "raster")
# Runtime/driver calls that start GPU work: kernels, graphs, copies and fills.
LAUNCH_CALLS = ("cudaLaunchKernel", "cuLaunchKernel", "cudaGraphLaunch", "cudaMemcpy", "cudaMemset")


def resize_camera(cam: Camera, width: Optional[int], height: Optional[int]) -> Camera:
    """``cam`` for an image of ``width`` x ``height`` (each axis scaled on its own; None keeps it)."""
    w, h = width or cam.width, height or cam.height
    sx, sy = w / cam.width, h / cam.height
    return Camera(cam.viewmat, cam.fx * sx, cam.fy * sy, cam.cx * sx, cam.cy * sy, w, h, cam.near, cam.far)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_frames(fn: Callable[[int], object], frames: int, warmup: int, device: torch.device) -> List[float]:
    """Wall time in ms of each of ``frames`` calls ``fn(i)`` after ``warmup`` untimed ones (synchronised)."""
    for i in range(warmup):
        fn(i)
    times = []
    for i in range(frames):
        _sync(device)
        t0 = time.perf_counter()
        fn(i)
        _sync(device)
        times.append((time.perf_counter() - t0) * 1e3)
    return times


def count_launches(fn: Callable[[int], object], frames: int, device: torch.device) -> Optional[float]:
    """Launches (kernels, graph launches, copies, fills) per call of ``fn`` over ``frames`` calls on CUDA, counted
    by torch.profiler; None on the CPU."""
    if device.type != "cuda":
        return None
    acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=acts) as prof:
        for i in range(frames):
            fn(i)
        torch.cuda.synchronize(device)
    calls = sum(e.count for e in prof.key_averages() if e.key.startswith(LAUNCH_CALLS))
    return calls / frames


def _gsplat_raster(means, quats, scales, opacities, colors, cam: Camera):
    import gsplat

    dev = means.device
    K = torch.tensor([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], dtype=torch.float32, device=dev)
    return gsplat.rasterization(means, quats, scales, opacities, colors,
                               cam.viewmat.to(device=dev, dtype=torch.float32)[None], K[None], cam.width,
                               cam.height, near_plane=cam.near, rasterize_mode="classic")[0]


def benchmark(run: Path, device: Optional[str] = None, width: Optional[int] = None, height: Optional[int] = None,
              frames: int = 100, warmup: int = 10, vs_gsplat: bool = False,
              launch_frames: int = 5, white_balance: Optional[str] = None) -> Dict[str, object]:
    """Median ms / FPS of the full enhanced render (torch path and fused path) and of the rasterization alone
    for ``run``; on CUDA also the launches per frame of the two full stages (over ``launch_frames`` frames).
    ``white_balance``: a ``--white-balance`` form, timed as the stage "fused + balance"."""

    cfg, scene, model, step = load_run(run, device)
    model.eval()
    views = scene.test or scene.train
    cams = [resize_camera(view_camera(v), width, height) for v in views]
    degree = active_sh_degree(cfg, step)
    g = model.gaussians
    dev = g.means.device
    if len(g) == 0:
        raise UserError(f"run {run} has no Gaussians to render")

    def full(i: int) -> None:
        model.render(cams[i % len(cams)], degree)

    renderer = InferenceRenderer(model, degree)

    def fused(i: int) -> None:
        renderer.render(cams[i % len(cams)])

    # The 6 channels of every view, computed once: the rasterizer alone then sees exactly the same work.
    with torch.no_grad():
        means, quats, scales, opac = g.means, g.quats, g.scales, g.opacities
        channels = [model.channels(cam.center.to(means), degree).contiguous() for cam in cams]

    def raster(i: int) -> None:
        rasterize_gaussians(means, quats, scales, opac, channels[i % len(cams)], cams[i % len(cams)])

    stages: Dict[str, Callable[[int], None]] = {"full": full, "full (fused)": fused, "raster": raster}
    if dev.type == "cuda":  # the same frame with the colour kernel after the binning, not beside it
        serial = InferenceRenderer(model, degree)
        serial.overlap_colors = False
        stages["fused, serial"] = lambda i: serial.render(cams[i % len(cams)])
        culled = InferenceRenderer(model, degree)
        culled.cull_tiles = True
        stages["fused, tile cull"] = lambda i: culled.render(cams[i % len(cams)])
    balance_text = None
    if white_balance is not None:
        wb = parse_white_balance(white_balance)
        balance = white_balance_of(wb, model, cfg, scene, degree)
        balance_text = describe_balance(wb, balance)
        if cfg.method == "retinexgs" and renderer.can_balance():
            # the same call as "full (fused)" with the balance (render and the viewer pass it so, through
            # render_function): the frame's own cost of the edit
            fixed = torch.as_tensor(balance, dtype=torch.float32)
            stages["fused + balance"] = lambda i: renderer.render(cams[i % len(cams)], balance=fixed)
        else:  # no fused balance for this tone: the light balanced and encoded again in torch
            balanced = render_function(model, cfg, degree, renderer=InferenceRenderer(model, degree),
                                       balance=balance)
            stages["fused + balance"] = lambda i: balanced(cams[i % len(cams)])
    if vs_gsplat:
        def gs(i: int) -> None:
            _gsplat_raster(means, quats, scales, opac, channels[i % len(cams)], cams[i % len(cams)])
        stages["raster (gsplat)"] = gs
    out: Dict[str, object] = {"gaussians": len(g), "width": cams[0].width, "height": cams[0].height,
                              "channels": int(channels[0].shape[1]), "frames": frames,
                              "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
                              "fused_colors": renderer.fused, "colors_note": renderer.fallback_reason,
                              "white_balance": balance_text}
    with torch.no_grad():  # the fused path must give the torch path's image
        ref, got = model.render(cams[0], degree)["rgb"], renderer.render(cams[0])["rgb"]
        out["fused_max_abs_diff"] = float((ref.double() - got.double()).abs().max()) if ref.numel() else 0.0
    with torch.no_grad():
        for name, fn in stages.items():
            ms = statistics.median(time_frames(fn, frames, warmup, dev))
            out[name] = {"ms": ms, "fps": 1e3 / ms}
            if name.startswith("full") and launch_frames > 0:
                out[name]["launches"] = count_launches(fn, launch_frames, dev)
    return out


def format_result(r: Dict[str, object]) -> str:
    """The side-by-side table of :func:`benchmark`'s result."""
    lines = [f"{r['device']}: {r['gaussians']} Gaussians, {r['width']}x{r['height']}, {r['channels']} channels, "
             f"median of {r['frames']} frames"]
    full = r["full"]["ms"]  # type: ignore[index]
    for name in [k for k in r if isinstance(r[k], dict)]:
        stage = r[name]
        ms = stage["ms"]  # type: ignore[index]
        launches = stage.get("launches")  # type: ignore[union-attr]
        extra = f", {launches:.0f} launches/frame" if launches is not None else ""
        lines.append(f"  {name:<16} {ms:8.3f} ms  {1e3 / ms:8.1f} FPS  ({ms / full:5.2f} of full{extra})")
    raster = r["raster"]["ms"]  # type: ignore[index]
    fused = r["full (fused)"]["ms"]  # type: ignore[index]
    lines.append(f"  MLP + EnhancementNet + SH share of the full render: {100 * (full - raster) / full:.0f} % "
                 f"(torch), {100 * (fused - raster) / fused:.0f} % (fused)")
    lines.append(f"  fused / torch full render: {fused / full:.2f}x time, {full / fused:.1f}x FPS"
                 + ("" if r.get("fused_colors", True) else f" (torch colours: {r.get('colors_note')})")
                 + f"; max |fused - torch| of the enhanced image: {r.get('fused_max_abs_diff', float('nan')):.2e}")
    if "fused + balance" in r:
        ratio = r["fused + balance"]["ms"] / fused  # type: ignore[index]
        lines.append(f"  white balance ({r['white_balance']}): {ratio:.3f}x the fused frame's time "
                     f"({100 * (ratio - 1):+.1f} %)")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m retinexgs.bench fps", description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, type=Path, help="a trained run folder")
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--width", type=int, default=None)
    parser.add_argument("--height", type=int, default=None)
    parser.add_argument("--frames", type=int, default=100, help="timed frames (default 100)")
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--vs", choices=["gsplat"], default=None, help="also time gsplat's rasterization")
    parser.add_argument("--launch-frames", type=int, default=5,
                        help="frames profiled to count launches per frame on CUDA (0: skip; default 5)")
    parser.add_argument("--white-balance", default=None, metavar="FORM",
                        help="also time the fused frame with this render-time white balance (render's forms)")
    args = parser.parse_args(argv)
    if args.frames < 1 or args.warmup < 0 or args.launch_frames < 0 or any(
            size is not None and size < 1 for size in (args.width, args.height)):
        parser.error("--frames, --width and --height must be at least 1, --warmup and --launch-frames at least 0")

    try:
        print(format_result(benchmark(args.run, args.device, args.width, args.height, args.frames, args.warmup,
                                      args.vs == "gsplat", args.launch_frames, args.white_balance)))
    except UserError as exc:
        print(f"bench fps: error: {exc}")
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
