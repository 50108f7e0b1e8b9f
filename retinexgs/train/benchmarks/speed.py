"""Training-step speed: wall time split into GPU busy time and host overhead, and its growth with Gaussian count,
for our rasterizer and for gsplat's in the same step, side by side.

    python -m retinexgs.bench train-speed --device cuda [--vs gsplat] [--sizes 100k,1M,3M] [--width 1280 --height 720]
    python -m retinexgs.bench train-speed --device cuda --data SCENE [--config NAME] [--steps 300]

Synthetic sweep (the default): random Gaussians (:mod:`retinexgs.demo.splats`) with the default config's
illumination MLP and SH degree 3, one camera, random targets for R, L and S. One step is what the trainer does
before the enhancement losses start: per-Gaussian SH colours and illumination MLP, one 6-channel rasterization,
the supervision (L1 + SSIM of R̂, L̂ and R̂∘L̂), TV and SH losses, backward, the trainer's Adam. The gsplat step is the
same step with ``gsplat.rasterization`` in place of ours (same colours, same loss), so the ratio is the
rasterizer's share; no density control in either.

``--data`` times the real :class:`~retinexgs.train.trainer.Trainer` on a scene instead (density control and the
enhancement losses included, as the config schedules them), after ``--warmup`` steps.

"wall" is the median step with a device synchronisation after each step; "free-running" is the mean step without
those synchronisations (what training sees); "GPU" is the time the GPU is busy per step (the union of the kernels'
copies' and memsets' spans in a ``torch.profiler`` trace, a separate pass; GPU-side annotations, which span
gaps, are left out); "overhead" = wall − GPU: the time the GPU waits for the host (Python, launches, syncs).
Launches (kernels and graph replays) per step come from the same trace. Where the GPU time comes out above the
free-running step, the split is flagged as unreliable instead of printed as a negative overhead.
"""
from __future__ import annotations

import argparse
import math
import random
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import torch

from retinexgs.demo.splats import orbit_camera, random_scene
from retinexgs.render import Camera, rasterize_gaussians
from retinexgs.model.gaussians import GaussianModel
from retinexgs.train.adam import adam_for
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.train import losses
from retinexgs.run.config import load_config
from retinexgs.run.folder import open_scene
from retinexgs.train.sfm_preview import scene_sfm_denoise
from retinexgs.train.trainer import Trainer
from retinexgs.errors import UserError


def parse_size(text: str) -> int:
    """'100k' -> 100000, '3M' -> 3000000, '2500' -> 2500."""
    t = text.strip().lower()
    mult = {"k": 1_000, "m": 1_000_000}.get(t[-1:], 1)
    value = float(t[:-1] if mult > 1 else t)
    if value <= 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"not a Gaussian count: {text!r}")
    return int(value * mult)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _device_time_us(event) -> float:
    for name in ("self_device_time_total", "self_cuda_time_total"):
        if hasattr(event, name):
            return float(getattr(event, name))
    return 0.0


def busy_ms(intervals: List[Tuple[float, float]]) -> float:
    """Length in ms of the union of (start, end) intervals in µs: kernels that overlap (streams) or appear twice in
    the trace (a graph's replay lists its kernels) count once."""
    total, end = 0.0, float("-inf")
    for a, b in sorted(intervals):
        if b <= end:
            continue
        total += b - max(a, end)
        end = b
    return total / 1e3


GPU_WORK = ("kernel", "gpu_memcpy", "gpu_memset")  # Kineto activity types that occupy the GPU


def _is_gpu_work(event) -> bool:
    """A kernel, copy or memset on the GPU, and not a GPU-side *annotation*: torch mirrors each
    ``record_function`` range (``Optimizer.step``, ...) onto the GPU timeline as a span from its first kernel to
    its last, gaps included, so counting those made the "GPU time" exceed the step's wall time."""
    kind = getattr(event, "activity_type", None)
    if isinstance(kind, str) and kind:
        return kind in GPU_WORK
    return (getattr(event, "device_type", None) == torch.autograd.DeviceType.CUDA
            and not getattr(event, "is_user_annotation", False))


def profile_steps(step: Callable[[], None], steps: int, device: torch.device) -> Dict[str, float]:
    """GPU busy ms per step (the union of the kernels', copies' and memsets' time spans) and kernel or graph
    launches per step over ``steps`` profiled steps."""
    if device.type != "cuda":
        return {"gpu_ms": float("nan"), "launches": float("nan")}
    acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    _sync(device)
    with torch.profiler.profile(activities=acts) as prof:
        for _ in range(steps):
            step()
        _sync(device)
    spans, launches = [], 0
    for e in prof.events():
        if e.name.startswith(("cudaLaunchKernel", "cuLaunchKernel", "cudaGraphLaunch")):
            launches += 1
        elif _is_gpu_work(e) and e.time_range.end > e.time_range.start:
            spans.append((float(e.time_range.start), float(e.time_range.end)))
    return {"gpu_ms": busy_ms(spans) / steps, "launches": launches / steps}


def time_steps(step: Callable[[], None], steps: int, device: torch.device) -> float:
    """Median wall ms of ``steps`` calls, each followed by a synchronisation."""
    times = []
    for _ in range(steps):
        _sync(device)
        t0 = time.perf_counter()
        step()
        _sync(device)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def measure(step: Callable[[], None], steps: int, warmup: int, device: torch.device) -> Dict[str, float]:
    """wall / GPU / overhead ms and launches per step, plus the free-running ms per step (no per-step sync)."""
    for _ in range(warmup):
        step()
    wall = time_steps(step, steps, device)
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    _sync(device)
    free = (time.perf_counter() - t0) * 1e3 / steps
    prof = profile_steps(step, max(3, min(steps, 10)), device)
    gpu = prof["gpu_ms"]
    # The GPU cannot be busy longer per step than a free-running step lasts: if the trace says so, its spans are
    # not what the GPU did (5 % slack for the profiler's own cost) and no overhead is derived from them.
    reliable = not math.isfinite(gpu) or gpu <= 1.05 * free
    return {"wall_ms": wall, "free_ms": free, "gpu_ms": gpu, "overhead_ms": wall - gpu if reliable else math.nan,
            "launches": prof["launches"], "split_ok": reliable}


# ---- the synthetic step -----------------------------------------------------------------------------------
def _gsplat_rasterize(means, quats, scales, opacities, colors, cam: Camera) -> torch.Tensor:
    import gsplat

    dev = means.device
    K = torch.tensor([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], dtype=torch.float32, device=dev)
    image, _, _ = gsplat.rasterization(means, quats, scales, opacities, colors,
                                       cam.viewmat.to(device=dev, dtype=torch.float32)[None], K[None], cam.width,
                                       cam.height, near_plane=cam.near, rasterize_mode="classic")
    return image[0]


def synthetic_step(n: int, width: int, height: int, device: torch.device, rasterizer: str = "ours",
                   seed: int = 0) -> Callable[[], None]:
    """One training step of a random scene of ``n`` Gaussians (see the module docstring), as a closure."""

    cfg = load_config()
    sc = random_scene(n, 3, seed)
    k = sc["sh"].shape[1]
    params = {"means": sc["means"], "quats": sc["quats"], "log_scales": sc["scales"].log(),
              "opacity_logits": torch.logit(sc["opacities"]), "sh_dc": sc["sh"][:, :1].contiguous(),
              "sh_rest": sc["sh"][:, 1:k].contiguous()}
    model = RetinexGSModel(GaussianModel(params, 3), cfg.model, decomposed=True).to(device)
    cam = orbit_camera(width, height)
    g = torch.Generator().manual_seed(seed + 1)
    R_t, L_t = (torch.rand(1, 3, height, width, generator=g).to(device) for _ in range(2))
    L_t = L_t[:, :1]
    S_t = R_t * L_t
    opt = adam_for(device, [{"params": list(model.parameters()), "lr": 1e-3}], eps=1e-15)  # the trainer's Adam
    c = cfg.loss
    gm = model.gaussians
    center = cam.center.to(device)

    def step() -> None:
        colors = model.channels(center, 3)
        if rasterizer == "gsplat":
            image = _gsplat_rasterize(gm.means, gm.quats, gm.scales, gm.opacities, colors, cam)
        else:
            image = rasterize_gaussians(gm.means, gm.quats, gm.scales, gm.opacities, colors, cam,
                                        validate=False).image
        R_hat, L_hat = losses.to_bchw(image[..., :3]), losses.to_bchw(image[..., 3:6])
        sup, _ = losses.supervision_loss(R_hat, L_hat, R_t, L_t, S_t, c.w_r, c.w_l, c.w_s,
                                         c.lambda_ssim)
        loss = sup + c.w_tv * losses.tv_loss(R_hat) + c.w_sh * losses.sh_sparsity_loss(gm.sh_rest)
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    return step


def trainer_step(scene_path: Path, config: List[str], device: torch.device, run_dir: Path,
                 overrides: Optional[List[str]] = None) -> Callable[[], None]:
    """The real trainer's next step on ``scene_path`` (it keeps training across calls); ``overrides``: --set
    key=value items (e.g. ``train.stream_views=always``)."""

    cfg = load_config(config, list(overrides or []))
    # The scene as train opens it (a bare night folder's SfM through data.sfm_denoise's previews)
    scene = open_scene(scene_path, cfg, sfm_denoise=scene_sfm_denoise(cfg.data.sfm_denoise))
    tr = Trainer(cfg, scene, run_dir, str(device), progress=False, log=lambda s: None)

    def step() -> None:  # the body of Trainer.train's loop, without its logging and checkpoints
        if not tr.order:
            tr.order = list(range(len(tr.views)))
            random.shuffle(tr.order)
        tr.step += 1
        tr.train_step(tr.step, tr.views[tr.order.pop()])

    step.trainer = tr  # type: ignore[attr-defined]
    return step


def profile_events(step: Callable[[], None], events: int, device: torch.device, top: int = 15) -> str:
    """What a density event costs: ``events`` times, train up to the step before the next scheduled event, then
    time (synchronised) the event's step and the one after it (its re-captures) under ``torch.profiler``, and as
    many pairs of plain steps right after; returns the wall ms per pair of each and the host calls (CPU ops and
    CUDA runtime calls) whose self time per pair grew most, as a table."""
    tr = step.trainer  # type: ignore[attr-defined]
    sched = tr.schedule

    def is_event(s: int) -> bool:
        return sched.densify_at(s) or sched.reset_at(s)

    acts = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA]
                                                    if device.type == "cuda" else [])
    totals: Dict[str, List[float]] = {"event": [], "plain": []}
    selfs: Dict[str, Dict[str, float]] = {"event": {}, "plain": {}}
    done = 0
    while done < events and tr.step < tr.cfg.steps - 4:
        if not is_event(tr.step + 1) or is_event(tr.step + 2):
            step()
            continue
        for kind in ("event", "plain"):
            if kind == "plain" and (is_event(tr.step + 1) or is_event(tr.step + 2)):
                break
            _sync(device)
            with torch.profiler.profile(activities=acts) as prof:
                t0 = time.perf_counter()
                step()
                step()
                _sync(device)
                totals[kind].append((time.perf_counter() - t0) * 1e3)
            for e in prof.key_averages():
                selfs[kind][e.key] = selfs[kind].get(e.key, 0.0) + e.self_cpu_time_total / 1e3
        else:
            done += 1
    if not totals["event"] or len(totals["plain"]) < len(totals["event"]):
        return "no density event in reach (start --warmup inside the densification window)"
    k = len(totals["event"])
    ev, pl = statistics.median(totals["event"]), statistics.median(totals["plain"][:k])
    lines = [f"{k} density events (the event's step and the next) against as many pairs of plain steps right "
             f"after: {ev:.2f} against {pl:.2f} ms per pair (medians): {ev - pl:.2f} ms an event",
             "| host call (self CPU time) | event pair ms | plain pair ms | difference |", "|---|---|---|---|"]
    keys = set(selfs["event"]) | set(selfs["plain"])
    diff = sorted(keys, key=lambda key: selfs["plain"].get(key, 0.0) - selfs["event"].get(key, 0.0))
    for key in diff[:top]:
        a, b = selfs["event"].get(key, 0.0) / k, selfs["plain"].get(key, 0.0) / k
        lines.append(f"| {key[:70]} | {a:.2f} | {b:.2f} | {a - b:+.2f} |")
    return "\n".join(lines)


def _row(label: str, m: Dict[str, float], ref: Optional[Dict[str, float]] = None) -> str:
    def f(x: float) -> str:
        return "n/a" if not math.isfinite(x) else f"{x:.2f}"
    ratio = f" | {m['wall_ms'] / ref['wall_ms']:.2f}" if ref else ""
    gpu = f(m["gpu_ms"]) + ("" if m.get("split_ok", True) else " (above free-running: unreliable)")
    return (f"| {label} | {f(m['wall_ms'])} | {f(m['free_ms'])} | {gpu} | {f(m['overhead_ms'])} | "
            f"{f(m['launches'])}{ratio} |")


HEADER = "| case | wall ms/step | free-running ms/step | GPU ms/step | overhead ms/step | launches/step"


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m retinexgs.bench train-speed",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", choices=["cpu", "cuda"])
    parser.add_argument("--vs", choices=["gsplat"], default=None, help="also time the gsplat-based step")
    parser.add_argument("--sizes", default="100k,1M,3M", help="Gaussian counts, comma-separated (100k, 1M, ...)")
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--steps", type=int, default=20, help="timed steps per case")
    parser.add_argument("--warmup", type=int, default=5, help="untimed steps first (with --data: e.g. 3000 "
                        "to time the phase with the enhancement losses)")
    parser.add_argument("--data", type=Path, default=None, help="time the real trainer on this scene instead")
    parser.add_argument("--config", action="append", default=[], help="config name(s) for --data")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="config override for --data (e.g. train.stream_views=always); repeatable")
    parser.add_argument("--events", type=int, default=0, help="with --data: also profile this many density events "
                        "against plain steps (what each costs, and the host calls that grew)")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.warmup < 0 or args.width < 1 or args.height < 1:
        parser.error("--steps, --width and --height must be at least 1 and --warmup at least 0")

    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("bench train-speed: error: --device cuda but torch sees no GPU (use --device cpu)")
        return 2
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"{name}, torch {torch.__version__}")
    if args.data is not None:
        with tempfile.TemporaryDirectory() as run:
            try:
                step = trainer_step(args.data, args.config, device, Path(run), args.set)
            except UserError as exc:
                print(f"bench train-speed: error: {exc}")
                return 2
            m = measure(step, args.steps, args.warmup, device)
            n = len(step.trainer.model.gaussians)  # type: ignore[attr-defined]
            last = step.trainer.step  # type: ignore[attr-defined]
            print(f"trainer on {args.data} ({' '.join(args.config + args.set) or 'default'}), steps 1-{last}, "
                  f"timed after step {args.warmup}; {n} Gaussians at the end")
            views = step.trainer.views  # type: ignore[attr-defined]
            if getattr(step.trainer, "streamed", False):  # type: ignore[attr-defined]
                print(f"views streamed: {views.hits} prefetched, {views.misses} loaded on demand; "
                      f"{views.slot_bytes / 2**20:.0f} MiB of view buffers on the device")
            else:
                print("views preloaded on the device")
            print(HEADER + " |\n|---|---|---|---|---|---|")
            print(_row("trainer", m))
            if args.events > 0:
                print(profile_events(step, args.events, device))
                graphs = step.trainer.channel_graphs  # type: ignore[attr-defined]
                if graphs is not None:
                    print(f"Gaussians' channel graphs: {graphs.captures} captures, {graphs.deferred} steps eager "
                          "(the Gaussians about to change)")
                    step.trainer.channel_graphs = None  # type: ignore[attr-defined]
                    eager = measure(step, args.steps, 0, device)
                    step.trainer.channel_graphs = graphs  # type: ignore[attr-defined]
                    print(_row("trainer, channels eager", eager, m) + " (wall ratio to the graphed step)")
        return 0
    try:
        sizes = [parse_size(s) for s in args.sizes.split(",") if s.strip()]
    except argparse.ArgumentTypeError as exc:
        parser.error(str(exc))
    print(f"synthetic step at {args.width}x{args.height}, SH degree 3 + illumination MLP, 6 channels, "
          f"median of {args.steps} steps after {args.warmup}")
    print(HEADER + (" | ours / gsplat wall |" if args.vs else " |"))
    print("|---|---|---|---|---|---|" + ("---|" if args.vs else ""))
    for n in sizes:
        ours = measure(synthetic_step(n, args.width, args.height, device), args.steps, args.warmup, device)
        if args.vs:
            theirs = measure(synthetic_step(n, args.width, args.height, device, "gsplat"), args.steps,
                             args.warmup, device)
            print(_row(f"{n:,} gsplat", theirs))
            print(_row(f"{n:,} ours", ours, theirs))
        else:
            print(_row(f"{n:,} ours", ours))
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
