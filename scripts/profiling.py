"""Where the time goes: profiles of training steps, frames and the rasterizer, operator counts, LR3M timings.

    python scripts/profiling.py train SCENE [--steps 300] [--profile 30] [--config NAME] [--set KEY=VALUE]
    python scripts/profiling.py frame RUN [--frames 50] [--fused]
    python scripts/profiling.py raster [--repeats 10]
    python scripts/profiling.py ops [SCENE] [--device cpu|cuda] [--steps 300] [--profile 30] [--emulate-graphs]
    python scripts/profiling.py syncs [SCENE] [--device cpu|cuda] [--steps 300] [--profile 100]
    python scripts/profiling.py lr3m IMAGE
    python scripts/profiling.py ssim [--device cpu|cuda] [--shape 1,15,360,640] [--padding same|valid]

Modes (each one's ``--help`` says more):

- ``train`` (GPU): trains ``--steps`` warm-up steps (densification included, the enhancement losses switched on
  half way), then records ``--profile`` steps with torch.profiler: the mean wall time per step, kernel / graph
  launches, syncs and copies per step, and the top operators by CUDA and by CPU time.
- ``frame`` (GPU): the full enhanced render of a trained run: operators by CUDA and CPU time, launches per frame.
  ``--fused`` profiles the InferenceRenderer (fused colour kernel + CUDA-graph enhancement: what render, export
  and the viewer use) instead of ``model.render``.
- ``raster`` (GPU): the raster bench's forward (ours with and without input checks, gsplat when installed), per
  case and renderer: the wall time per forward and the CUDA kernels' total time per forward, largest first.
- ``ops`` (CPU or GPU): counts the operators of training steps as the backends see them, per step and by name (a
  proxy for kernel launches; a small synthetic scene without SCENE). Run it on the CPU before and after a change.
- ``syncs`` (CPU or GPU): host reads of tensor values (a sync each on the GPU) per training step, by the line that
  made them and by the step's kind; the ordinary step should make none. On CUDA also torch's sync debug warnings.
- ``lr3m`` (GPU): times LR3M variants on one image; prints the fastest setting as ``--set`` overrides.
- ``ssim`` (CPU or GPU): SSIM's Gaussian filter, forward + backward, ours vs the 2-D depthwise reference and
  candidates (channels as a batch, banded matrix products whole or in tiles, sums of shifted slices): time, ratio and largest difference;
  then the training SSIM itself: the five moments in one call, the torch twin (x's and y's split) and the fused kernels.

``scripts/device.sh speed`` runs the GPU modes on the device machine (its stages profile, fprofile, rprofile, lr3m).
"""
from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch

from retinexgs.bench.args import image_size


# ---------------------------------------------------------------------------------------------------- train
def profile_train(args: argparse.Namespace) -> None:
    """Where a training step's time goes (GPU)."""
    from retinexgs.run.config import load_config
    from retinexgs.run.folder import open_scene
    from retinexgs.train.trainer import Trainer

    cfg = load_config(args.config, [f"loss.enhance_from={args.steps // 2}"] + args.overrides)
    scene = open_scene(args.scene, cfg)
    with tempfile.TemporaryDirectory() as run:
        tr = Trainer(cfg, scene, Path(run), "cuda", progress=False, log=lambda s: None)
        tr.train(stop_after=args.steps)
        # A session's last step always writes a checkpoint (~50 device->host copies, a disk write): not part of
        # the step being measured, so the timed and profiled windows below write none (`syncs` mode: per step).
        tr.save = lambda: None
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        tr.train(stop_after=args.profile)
        torch.cuda.synchronize()
        print(f"{(time.perf_counter() - t0) / args.profile * 1e3:.2f} ms per step (unprofiled), "
              f"{len(tr.model.gaussians)} Gaussians")
        if getattr(args, "slack", 0):
            print_slack(tr, args.profile, args.slack)
        acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
        with torch.profiler.profile(activities=acts) as prof:
            tr.train(stop_after=args.profile)
            torch.cuda.synchronize()
        table = prof.key_averages()
        launches = sum(e.count for e in table if e.key.startswith(("cudaLaunchKernel", "cuLaunchKernel")))
        graph_launches = sum(e.count for e in table if e.key.startswith("cudaGraphLaunch"))
        syncs = sum(e.count for e in table if "Synchronize" in e.key or e.key == "cudaMemcpyAsync")
        print(f"{launches / args.profile:.1f} kernel launches, {graph_launches / args.profile:.1f} graph launches, "
              f"{syncs / args.profile:.1f} syncs/memcpys per step")
        # The copies by direction (device->device copies, e.g. into a CUDA graph's inputs, do not sync).
        copies = {e.key: e.count for e in table if e.key.startswith("Memcpy")}
        print("  copies per step: " + (", ".join(f"{k} {v / args.profile:.2f}" for k, v in sorted(copies.items()))
                                       or "none") + "; synchronize calls per step: "
              + f"{sum(e.count for e in table if 'Synchronize' in e.key) / args.profile:.2f}")
        print(table.table(sort_by="cuda_time_total", row_limit=25))
        # The kernels by their own GPU time (what a fused or faster kernel would save), most first.
        print(table.table(sort_by="self_cuda_time_total", row_limit=args.rows))
        print(table.table(sort_by="cpu_time_total", row_limit=20))
        print_gpu_idle(prof, args.profile)
        if getattr(args, "host", False):
            print_host_profile(tr, args.profile)


def print_slack(tr, steps: int, extra_us: float) -> None:
    """Which side bounds the step: the unprofiled step timed again with ``extra_us`` more work a step on the GPU
    (a spin kernel, ``torch.cuda._sleep``) and then on the host (a busy wait). The side whose extra work lengthens
    the step by about ``extra_us`` is the critical path; the other's slack is ``extra_us`` minus its lengthening."""
    start, stop = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    cycles = 1_000_000
    start.record()
    torch.cuda._sleep(cycles)
    stop.record()
    torch.cuda.synchronize()
    per_us = cycles / (start.elapsed_time(stop) * 1e3)  # the spin kernel's cycles per microsecond
    step = tr.train_step

    def timed(extra) -> float:
        def wrapped(*a, **k):
            extra()
            return step(*a, **k)
        tr.train_step = wrapped
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        tr.train(stop_after=steps)
        torch.cuda.synchronize()
        tr.train_step = step
        return (time.perf_counter() - t0) / steps * 1e6

    def host_spin() -> None:
        until = time.perf_counter() + extra_us * 1e-6
        while time.perf_counter() < until:
            pass

    base = timed(lambda: None)
    gpu = timed(lambda: torch.cuda._sleep(int(extra_us * per_us)))
    host = timed(host_spin)
    again = timed(lambda: None)
    print(f"slack probe, {steps} steps each: step {base:.0f} µs (again {again:.0f}); +{extra_us:.0f} µs on the GPU: "
          f"{gpu:.0f} µs (+{gpu - base:.0f}); +{extra_us:.0f} µs on the host: {host:.0f} µs (+{host - base:.0f})")


def print_host_profile(tr, steps: int) -> None:
    """The host's time by Python function over ``steps`` training steps (cProfile; its own overhead inflates
    every call alike): where the GPU's idle gaps between phases come from."""
    import cProfile
    import gc
    import io
    import pstats

    spent: Dict[int, List[float]] = {}
    began: List[float] = []

    def timed(phase: str, info: dict) -> None:  # the collector's own time, by generation
        if phase == "start":
            began.append(time.perf_counter())
        elif began:
            spent.setdefault(info["generation"], []).append(time.perf_counter() - began.pop())

    gc.callbacks.append(timed)
    pr = cProfile.Profile()
    torch.cuda.synchronize()
    pr.enable()
    tr.train(stop_after=steps)
    pr.disable()
    torch.cuda.synchronize()
    gc.callbacks.remove(timed)
    print("garbage collections over the steps: " + (", ".join(
        f"generation {g}: {len(t)} taking {sum(t) * 1e3:.2f} ms" for g, t in sorted(spent.items())) or "none"))
    for key in ("tottime", "cumulative"):
        out = io.StringIO()
        pstats.Stats(pr, stream=out).sort_stats(key).print_stats(30)
        print(f"host functions by {key} over {steps} steps:")
        print("\n".join(line for line in out.getvalue().splitlines() if line.strip())[:9000])


def print_gpu_idle(prof, steps: int) -> None:
    """The GPU's timeline over the profiled steps: the share of the window some kernel or copy ran, and the idle
    gaps summed by the pair of kernels around them, most first (a gap waits on the host, or is the latency between
    a graph's dependent kernels)."""
    cuda = torch.autograd.DeviceType.CUDA
    spans = sorted((e.time_range.start, e.time_range.end, e.name) for e in prof.events()
                   if e.device_type == cuda and not e.name.startswith("step/")
                   and e.time_range.end > e.time_range.start)
    if not spans:
        print("no GPU activity in the profile")
        return
    busy, gaps = 0.0, {}
    start, end, last = spans[0][0], spans[0][1], spans[0][2]
    for s0, s1, name in spans[1:]:
        if s0 > end:  # an idle gap: the GPU had nothing queued between `last` and `name`
            busy += end - start
            key = (last[:48], name[:48])
            t, c = gaps.get(key, (0.0, 0))
            gaps[key] = (t + s0 - end, c + 1)
            start = s0
        if s1 >= end:
            end, last = s1, name
    busy += end - start
    window = spans[-1][1] - spans[0][0]
    idle = sum(t for t, _ in gaps.values())
    count = sum(c for _, c in gaps.values())
    print(f"GPU timeline: {window / steps / 1e3:.2f} ms a step, busy {busy / steps / 1e3:.2f} ms "
          f"({100 * busy / window:.0f} %), idle {idle / steps / 1e3:.2f} ms in {count / steps:.1f} gaps")
    print("largest idle gaps, summed a step (µs, count a step): after -> before")
    for (a, b), (t, c) in sorted(gaps.items(), key=lambda kv: -kv[1][0])[:15]:
        print(f"  {t / steps:8.1f} µs {c / steps:5.2f}  {a} -> {b}")


# ---------------------------------------------------------------------------------------------------- frame
def profile_frame(args: argparse.Namespace) -> None:
    """The full enhanced render of a trained run (GPU)."""
    from retinexgs.model.inference import InferenceRenderer
    from retinexgs.run.folder import load_run
    from retinexgs.run.render import active_sh_degree, view_camera

    cfg, scene, model, step = load_run(args.run, "cuda")
    model.eval()
    cams = [view_camera(v) for v in (scene.test or scene.train)]
    degree = active_sh_degree(cfg, step)
    if args.fused:
        renderer = InferenceRenderer(model, degree)
        frame = lambda cam: renderer.render(cam)  # noqa: E731
    else:
        frame = lambda cam: model.render(cam, degree)  # noqa: E731
    with torch.no_grad():
        for i in range(10):
            frame(cams[i % len(cams)])
        torch.cuda.synchronize()
        acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
        with torch.profiler.profile(activities=acts) as prof:
            for i in range(args.frames):
                frame(cams[i % len(cams)])
            torch.cuda.synchronize()
    table = prof.key_averages()
    launches = sum(e.count for e in table if e.key.startswith(("cudaLaunchKernel", "cuLaunchKernel")))
    print(f"{launches / args.frames:.1f} kernel launches per frame")
    print(table.table(sort_by="cuda_time_total", row_limit=30))
    print(table.table(sort_by="cpu_time_total", row_limit=30))


# --------------------------------------------------------------------------------------------------- raster
def profile_raster(args: argparse.Namespace) -> None:
    """Kernel-level profile of the raster bench's forward, per case (GPU)."""
    from torch.profiler import ProfilerActivity, profile

    from retinexgs.bench.raster_ours import render_ours, render_ours_unchecked
    from retinexgs.bench.raster_cuda import CASES, render_gsplat
    from retinexgs.demo.splats import orbit_camera, random_scene

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


# ------------------------------------------------------------------------------------------------------ ops
OPS_DOC = """Count the operators of RetinexGS training steps, per step and by name (a proxy for kernel launches).

Without SCENE a small synthetic scene is generated (96x72, 4000 points). Trains ``--steps`` warm-up steps
with the enhancement losses switched on half way (as the ``train`` mode does), then counts the
operators of ``--profile`` more steps and prints, per step:
  - aten operators as the backends see them (a TorchDispatchMode below autograd: the backward's operators
    are included, a composite operator counts as the operators it is made of), by name;
  - "kernel" operators: the same without the metadata-only ones (views, reshapes, empty tensors), each of
    which is (about) one kernel launch on the GPU, split by the trainer's phases (its
    ``record_function("step/...")`` ranges) and with the optimiser step apart (fused on the GPU);
  - the calls into the project's own kernels (retinexgs._C);
  - host syncs: aten::_local_scalar_dense (.item(), bool(), int() of a tensor), device->host copies;
  - CUDA graph replays (the image losses: one graph launch; the Gaussians' channels: two, forward and
    backward); on the CPU ``--emulate-graphs`` runs that path eagerly and counts what the graphs hold;
  - on CUDA also cudaLaunchKernel / cudaGraphLaunch counts and cudaMemcpy / synchronize calls (profiler).
Run it on the CPU before and after a change to compare; on the GPU it also shows the launches.
"""

# Operators that only make a new view or an uninitialised tensor: no kernel on any device.
METADATA = {
    "view", "_reshape_alias", "reshape", "as_strided", "slice", "select", "permute", "unsqueeze", "squeeze",
    "expand", "t", "transpose", "detach", "detach_", "alias", "unbind", "split", "split_with_sizes", "chunk",
    "narrow", "empty", "empty_strided", "empty_like", "resolve_conj", "resolve_neg", "lift_fresh", "flatten",
    "unflatten", "expand_as", "view_as", "_unsafe_view", "result_type", "set_", "resize_", "contiguous",
    "is_nonzero", "broadcast_tensors", "movedim", "diagonal", "squeeze_", "unsqueeze_", "record_stream",
    "is_same_size", "sym_size", "sym_stride", "sym_numel", "sym_storage_offset", "dim", "size", "stride",
    "_to_copy_meta", "new_empty", "new_empty_strided", "_has_compatible_shallow_copy_type", "is_pinned",
}
SYNCS = {"_local_scalar_dense", "item"}


def _op_name(func) -> str:
    """'aten.mul.Tensor' -> 'mul'; 'profiler._record_function_enter_new.default' -> its full name."""
    parts = str(func).split(".")
    return parts[1] if parts[0] == "aten" and len(parts) > 1 else str(func)


def _call_site() -> str:
    """The innermost retinexgs frame on the Python stack ("?" where there is none: the autograd engine's backward
    of an eager step; a graphed loss's backward shows as its ``_step``)."""
    for frame in reversed(traceback.extract_stack()[:-2]):
        if "/retinexgs/" in frame.filename:
            return f"{frame.filename.split('/retinexgs/')[1]}:{frame.lineno} {frame.name}"
    return "?"


def _op_counter(min_numel: int = 0, sites: bool = False):
    """A TorchDispatchMode that counts every operator reaching a backend, by name and by the trainer's phase
    (built on first use: the dispatch-mode import is private torch API, needed by ``ops`` alone); with
    ``min_numel``, also the bytes of the operators whose largest tensor has at least that many elements (the
    per-pixel traffic: inputs and outputs, the project's own kernels not included), by phase or, with ``sites``,
    by the retinexgs line that called the operator."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class OpCounter(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            # with min_numel: the bytes each (phase or call site, op) reads and writes in tensors of >= min_numel
            # elements
            self.traffic: collections.Counter = collections.Counter()
            self.ops: collections.Counter = collections.Counter()
            self.phases: collections.Counter = collections.Counter()
            self.d2h = 0
            self.syncs = 0
            self._stack: List[str] = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            kwargs = kwargs or {}
            name = _op_name(func)
            if name.startswith("profiler._record_function_enter"):
                self._stack.append(str(args[0]))
            elif name.startswith("profiler._record_function_exit"):
                if self._stack:
                    self._stack.pop()
            else:
                self.ops[name] += 1
                phase = next((p for p in reversed(self._stack) if p.startswith("step/")), "step/(other)")
                if any(p.startswith("Optimizer.step") for p in self._stack):
                    phase = "step/optimizer"
                if name not in METADATA:
                    self.phases[phase] += 1
                if name in SYNCS and phase != "step/optimizer":  # the CPU's non-fused Adam reads its step count
                    self.syncs += 1
                if name in ("_to_copy", "copy_") and args and isinstance(args[0], torch.Tensor):
                    dst = kwargs.get("device")
                    if args[0].is_cuda and (dst is not None and torch.device(dst).type == "cpu"):
                        self.d2h += 1
            out = func(*args, **kwargs)
            if min_numel and name not in METADATA and not name.startswith("profiler."):
                tensors = [t for t in torch.utils._pytree.tree_leaves((args, kwargs, out))
                           if isinstance(t, torch.Tensor)]
                if max((t.numel() for t in tensors), default=0) >= min_numel:
                    where = _call_site() if sites else phase
                    self.traffic[(where, name)] += sum(t.numel() * t.element_size() for t in tensors)
            return out

    return OpCounter()


def count_calls(module, names, when=None) -> Dict[str, int]:
    """Wrap the functions ``names`` of ``module`` so that calls are counted (returns the live counter);
    ``when()``: count only while it returns True."""
    calls: Dict[str, int] = collections.Counter()
    for name in names:
        fn = getattr(module, name)

        def wrapped(*a, _fn=fn, _name=name, **k):
            if when is None or when():
                calls[_name] += 1
            return _fn(*a, **k)

        setattr(module, name, wrapped)
    return calls


def _warm_trainer(args: argparse.Namespace, tmp: str):
    """A Trainer on ``args.scene`` (default: a small synthetic scene made in ``tmp``) after ``args.steps`` steps,
    with its run folder in ``tmp``; the enhancement losses start halfway so that the profiled steps include them."""
    from retinexgs.run.config import load_config
    from retinexgs.run.folder import open_scene
    from retinexgs.train.trainer import Trainer

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    scene_path = args.scene
    if scene_path is None:
        from retinexgs.demo.synthetic import make_demo_scene
        width, height = getattr(args, "size", (96, 72))
        scene_path = make_demo_scene(Path(tmp) / "scene", n_train=6, n_test=1, width=width, height=height,
                                     n_points=4000)
    cfg = load_config(args.config, [f"loss.enhance_from={args.steps // 2}"] + args.overrides)
    scene = open_scene(scene_path, cfg)
    run = Path(tmp) / "run"
    run.mkdir()
    extra = {"emulate_graphs": True} if args.emulate_graphs else {}
    tr = Trainer(cfg, scene, run, device, progress=False, log=lambda s: None, **extra)
    tr.train(stop_after=args.steps)
    return tr, device


def _fused_curves_everywhere() -> None:
    """The tone curve through its kernel on the CPU too (it runs there only on the GPU): the CPU census then counts
    the operators the GPU runs (``fused_curve.runs_fused``, which the curve and the exposure meter ask)."""
    from retinexgs.model.tones import fused_curve
    fused_curve.runs_fused = lambda x: True


def count_ops(args: argparse.Namespace) -> None:
    """Operators per training step as the backends see them (CPU or GPU)."""
    from retinexgs.render import _backend

    if args.fused_curves:
        _fused_curves_everywhere()
    with tempfile.TemporaryDirectory() as tmp:
        tr, device = _warm_trainer(args, tmp)
        cuda = device.startswith("cuda")
        k = _backend.kernels()
        kernel_calls = count_calls(k, [n for n in dir(k) if not n.startswith("_") and callable(getattr(k, n))])
        graph_calls = count_calls(torch.cuda.CUDAGraph, ["replay"]) if cuda else {}
        # Reads of tensor values by the host (a sync on the GPU) and tensors built from host numbers (a
        # host->device copy on the GPU), whatever the device.
        pixels = max(v.camera.width * v.camera.height for v in tr.views) if args.traffic else 0
        counter = _op_counter(pixels, sites=args.traffic == "sites")
        # (the CPU's non-fused Adam reads each parameter's step count with .item(): not counted)
        outside_optim = lambda: not any(p.startswith("Optimizer.step") for p in counter._stack)  # noqa: E731
        host_reads = count_calls(torch.Tensor, ["tolist", "item"], outside_optim)
        host_tensors = count_calls(torch, ["tensor", "as_tensor"], outside_optim)
        first = tr.step + 1
        n = args.profile
        acts = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if cuda else [])
        if cuda:
            torch.cuda.synchronize()
        with torch.profiler.profile(activities=acts) as prof, counter:
            tr.train(stop_after=n)
            if cuda:
                torch.cuda.synchronize()
        kernel_ops = {k: v for k, v in counter.ops.items() if k not in METADATA}
        optim = counter.phases.get("step/optimizer", 0)
        graphed = sum(v for k, v in counter.phases.items() if k.endswith("_graph"))
        print(f"steps {first}..{tr.step} on {device}, {len(tr.model.gaussians)} Gaussians, "
              f"config {args.config or ['default']} {args.overrides}, "
              f"cuda_graphs={tr.cfg.train.cuda_graphs}")
        print(f"aten ops per step (all):          {sum(counter.ops.values()) / n:8.1f}")
        print(f"kernel ops per step (no views):   {sum(kernel_ops.values()) / n - optim / n:8.1f}"
              f"  (+ {optim / n:.1f} in the optimiser step: one fused kernel per group on the GPU)")
        if graphed:
            print(f"kernel ops per step outside graphs: {(sum(kernel_ops.values()) - optim - graphed) / n:8.1f}"
                  f"  (+ {graphed / n:.1f} inside the phases *_graph: 3 graph launches on the GPU)")
        print("  by phase: " + ", ".join(f"{p[5:]} {c / n:.1f}" for p, c in sorted(counter.phases.items())))
        print(f"retinexgs._C calls per step:      {sum(kernel_calls.values()) / n:8.1f}  "
              + ", ".join(f"{k} {v / n:.1f}" for k, v in sorted(kernel_calls.items())))
        print(f"host syncs per step: {counter.syncs / n:.2f} item/bool/int (optimiser apart; on CUDA 1 of them is "
              f"binning's pair count, read a render late from pinned host memory: no wait), "
              f"{counter.d2h / n:.2f} device->host copies")
        host = {**{f"Tensor.{k}": v for k, v in host_reads.items()},
                **{f"torch.{k}": v for k, v in host_tensors.items()}}
        print("host reads / tensors from host numbers per step: "
              + (", ".join(f"{k} {v / n:.2f}" for k, v in sorted(host.items()) if v) or "none"))
        if cuda:
            names = collections.Counter(e.name for e in prof.events())
            launches = sum(v for k, v in names.items() if k in ("cudaLaunchKernel", "cuLaunchKernel",
                                                                   "cudaLaunchKernelExC", "cuLaunchKernelEx"))
            memcpy = sum(v for k, v in names.items() if k.startswith("cudaMemcpy"))
            sync = sum(v for k, v in names.items() if "Synchronize" in k)
            print(f"CUDA per step: {launches / n:.1f} kernel launches, {names.get('cudaGraphLaunch', 0) / n:.2f} "
                  f"graph launches ({sum(graph_calls.values()) / n:.2f} replays), {memcpy / n:.2f} memcpy calls, "
                  f"{sync / n:.2f} synchronizes")
            copies = {k: v for k, v in names.items() if k.startswith("Memcpy")}  # by direction (DtoD: no sync)
            print("  copies per step: " + (", ".join(f"{k} {v / n:.2f}" for k, v in sorted(copies.items())) or "none"))
        if pixels:
            total = sum(counter.traffic.values()) / n / pixels
            print(f"\nper-pixel traffic (torch ops on tensors of >= {pixels} elements, the largest view; bytes read "
                  f"and written per pixel per step, the project's kernels apart): {total:.0f} B/px")
            groups: collections.Counter = collections.Counter()
            for (where, _), b in counter.traffic.items():
                groups[where.replace("step/", "")] += b
            print(f"  by {'call site' if args.traffic == 'sites' else 'phase'}: "
                  + ", ".join(f"{g} {b / n / pixels:.0f}" for g, b in groups.most_common(args.top)))
            for (where, name), b in counter.traffic.most_common(args.top):
                print(f"  {b / n / pixels:8.1f} B/px  {name:<18} {where.replace('step/', '')}")
        rows = sorted(kernel_ops.items(), key=lambda kv: -kv[1])[: args.top]
        print(f"\ntop {len(rows)} kernel ops per step (optimiser included):")
        for name, count in rows:
            print(f"  {count / n:8.2f}  {name}")


# ---------------------------------------------------------------------------------------------------- syncs
SYNCS_DOC = """Host reads of tensor values (each one a sync on the GPU) per training step, by call site.

Without SCENE a small synthetic scene is generated (96x72, 4000 points). Trains ``--steps`` warm-up steps with
the enhancement losses switched on half way (as the ``train`` mode does), then trains ``--profile`` more steps
inside retinexgs.bench.syncs.SyncFinder: .item() .tolist() .cpu() .numpy() .to(cpu), bool/int/float/index of a
tensor, nonzero / unique / masked_select / where(cond), repeat_interleave without output_size and boolean-mask
indexing are counted by the project line that called them, per step of each kind: ordinary (should be none),
first, check (logging / checkpoint), density (densify, prune, opacity reset), after_event (graph re-captures).
On CUDA torch's sync debug mode ("warn") also counts the syncs torch sees inside operators (cuda-sync), and
torch.profiler counts the CUDA runtime's synchronize calls of each step whoever made them (cuda-runtime: the
rasterizer's pair count, read by the extension itself, is one a render where binning re-measures its buffer;
training's other renders read it a render late, train.pair_margin). Exits 1 if an ordinary step read.
"""


def find_syncs(args: argparse.Namespace) -> int:
    """Host reads per training step by call site (CPU or GPU); 1 if an ordinary step made any."""
    from retinexgs.bench.syncs import SyncFinder

    with tempfile.TemporaryDirectory() as tmp:
        tr, device = _warm_trainer(args, tmp)
        cuda = device.startswith("cuda")
        # On CUDA nothing is ignored: the trainer's Adam is fused there (no step-count reads).
        finder = SyncFinder(cuda_warn=cuda, ignore_via=() if cuda else ("torch/optim/",), cuda_profile=cuda)
        unwatch = finder.watch_trainer(tr)
        first = tr.step + 1
        try:
            with finder:
                tr.train(stop_after=args.profile)
        finally:
            unwatch()
        print(f"steps {first}..{tr.step} on {device}, {len(tr.model.gaussians)} Gaussians, "
              f"config {args.config or ['default']} {args.overrides}")
        finder.report()
        return 1 if finder.ordinary() else 0


# ----------------------------------------------------------------------------------------------------- lr3m
def time_lr3m(args: argparse.Namespace) -> None:
    """LR3M variants on one image on the GPU; prints the fastest setting as KEY=VALUE overrides."""
    from retinexgs.data.images import load_image_tensor
    from retinexgs.retinex import get_decomposer

    img = load_image_tensor(args.image).cuda()
    best = None
    for name, params in [("gram40", {}), ("gram32", {"group_size": 32}), ("svd40", {"solver": "svd"})]:
        d = get_decomposer("lr3m", **params)
        d(img)  # warm-up
        torch.cuda.synchronize()
        t0 = time.time()
        d(img)
        torch.cuda.synchronize()
        dt = time.time() - t0
        print(f"lr3m {name}: {dt:.2f} s / image", flush=True)
        if best is None or dt < best[0]:
            best = (dt, params)
    print("BEST " + " ".join(f"--set decomposer.params.{k}={v}" for k, v in best[1].items()) + f" # {best[0]:.2f}")


# ----------------------------------------------------------------------------------------------------- ssim
def _const(key: tuple, build):
    """A candidate's constant, built once (a captured CUDA graph cannot hold its host->device copy)."""
    from retinexgs.evaluate.metrics import cached_constant

    return cached_constant(("profiling.ssim",) + key, build)


def _filter_2d(x: torch.Tensor, size: int, sigma: float, pad: int) -> torch.Tensor:
    """SSIM's Gaussian filter as one depthwise 2-D convolution ([C,1,K,K]): the reference the 1-D passes match."""
    import torch.nn.functional as F
    from retinexgs.evaluate.metrics import gaussian_window

    w = _const(("2d", x.shape[1], size, sigma, x.dtype, x.device), lambda: (
        lambda g: (g[:, None] * g[None, :]).expand(x.shape[1], 1, size, size).contiguous())(
        gaussian_window(size, sigma, x.dtype, x.device)))
    return F.conv2d(x, w, padding=pad, groups=x.shape[1])


def _filter_batched(x: torch.Tensor, size: int, sigma: float, pad: int) -> torch.Tensor:
    """Candidate: the channels as the batch of a 1-channel conv (cuDNN rather than the depthwise kernel)."""
    import torch.nn.functional as F
    from retinexgs.evaluate.metrics import gaussian_window

    b, c, h, w = x.shape
    g = _const(("g", size, sigma, x.dtype, x.device), lambda: gaussian_window(size, sigma, x.dtype, x.device))
    y = F.conv2d(x.reshape(b * c, 1, h, w), g.view(1, 1, 1, size), padding=(0, pad))
    y = F.conv2d(y, g.view(1, 1, size, 1), padding=(pad, 0))
    return y.reshape(b, c, *y.shape[-2:])


def _filter_matmul(x: torch.Tensor, size: int, sigma: float, pad: int) -> torch.Tensor:
    """Candidate: each 1-D pass as a product with a banded (Toeplitz) matrix (TF32 off: full float32)."""
    from retinexgs.evaluate.metrics import gaussian_window

    g = gaussian_window(size, sigma, x.dtype)

    def band(n: int) -> torch.Tensor:  # [n, n + 2 pad - size + 1]: input index by output index
        def build() -> torch.Tensor:
            k = torch.arange(n)[:, None] - torch.arange(n + 2 * pad - size + 1) + pad
            return torch.where((k >= 0) & (k < size), g[k.clamp(0, size - 1)], 0.0).to(x.device)
        return _const(("band", n, size, sigma, pad, x.dtype, x.device), build)
    y = x @ band(x.shape[-1])
    return band(x.shape[-2]).t() @ y


def _filter_tiled(x: torch.Tensor, size: int, sigma: float, pad: int, tile: int = 64) -> torch.Tensor:
    """Candidate: each 1-D pass as products of overlapping tiles (tile + size - 1 inputs) with one small band
    matrix [tile + size - 1, tile]: the matmul candidate's speed without its cost growing with the image width."""
    import torch.nn.functional as F
    from retinexgs.evaluate.metrics import gaussian_window

    def build() -> torch.Tensor:
        g = gaussian_window(size, sigma, x.dtype)
        k = torch.arange(tile + size - 1)[:, None] - torch.arange(tile)
        return torch.where((k >= 0) & (k < size), g[k.clamp(0, size - 1)], 0.0).to(x.device)
    band = _const(("tile", tile, size, sigma, x.dtype, x.device), build)

    def along_last(v: torch.Tensor) -> torch.Tensor:
        n = v.shape[-1]
        m = n + 2 * pad - size + 1
        nt = -(-m // tile)
        v = F.pad(v, (pad, nt * tile + size - 1 - n - pad))
        return (v.unfold(-1, tile + size - 1, tile) @ band).flatten(-2)[..., :m]

    return along_last(along_last(x).transpose(-1, -2)).transpose(-1, -2)


def _ssim_one_call(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The training SSIM with its five moments in one filter call (before x's and y's were split): the reference of
    the bench's SSIM rows."""
    from retinexgs.evaluate.metrics import gaussian_filter

    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mx, my, exx, eyy, exy = gaussian_filter(torch.cat([x, y, x * x, y * y, x * y], dim=1), 11, 1.5, 5).chunk(5, 1)
    sxx, syy, sxy = exx - mx * mx, eyy - my * my, exy - mx * my
    return (((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))).mean()


def _time_step(step, cuda: bool, repeats: int) -> Tuple[float, Optional[float]]:
    """Seconds per call of ``step`` (after warm-up) and, on CUDA, the GPU kernels' seconds per call (training
    replays the losses as a CUDA graph, where launches cost little)."""
    def sync() -> None:
        if cuda:
            torch.cuda.synchronize()

    for _ in range(3):
        step()
    sync()
    t0 = time.perf_counter()
    for _ in range(repeats):
        step()
    sync()
    wall = (time.perf_counter() - t0) / repeats
    if not cuda:
        return wall, None
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
        for _ in range(5):
            step()
        sync()
    us = sum(getattr(e, "self_device_time_total", getattr(e, "self_cuda_time_total", 0))
             for e in prof.key_averages() if e.device_type == torch.autograd.DeviceType.CUDA)
    return wall, max(us / 5 * 1e-6, 1e-9)


def _compare_and_time(name, step, ref, t_ref, cuda: bool, repeats: int, row):
    """One row of the ssim mode: ``step()`` -> (output, gradient) compared with the first row's (``ref``; this one
    becomes it when None) and timed; returns the (reference, reference time) for the next rows."""
    out, gx = step()
    if ref is None:
        ref = (out.detach(), gx.detach())
    err = max((out - ref[0]).abs().max().item(), (gx - ref[1]).abs().max().item())
    t = _time_step(step, cuda, repeats)
    t_ref = t_ref or t
    row(name, t, t_ref, err)
    return ref, t_ref


def time_ssim(args: argparse.Namespace) -> None:
    """SSIM's Gaussian filter (the five moments' channels of one training view), forward + backward: ours
    (retinexgs.evaluate.metrics.gaussian_filter) against the 2-D depthwise reference and candidates; per variant
    the time per forward+backward, its ratio to the reference, and the largest difference from the reference.
    Then the training SSIM itself (x learns, the target y is fixed): ours against the five moments in one call."""
    from retinexgs.evaluate.metrics import _shifted_sums, gaussian_filter, ssim

    device = torch.device(args.device)
    cuda = device.type == "cuda"
    if cuda:
        torch.backends.cuda.matmul.allow_tf32 = False  # the matmul candidates must stay float32 to compare
        torch.backends.cudnn.allow_tf32 = False
    shape = tuple(int(s) for s in args.shape.split(","))
    pad = args.window // 2 if args.padding == "same" else 0
    variants = {"2d-reference": _filter_2d, "ours": gaussian_filter, "batched": _filter_batched,
                "matmul": _filter_matmul, "shifted-sums": _shifted_sums, "tiled": _filter_tiled}
    gen = torch.Generator().manual_seed(0)
    x0 = torch.rand(shape, generator=gen, dtype=torch.float32).to(device)
    grad = torch.rand(x0.shape[:2] + tuple(s - 2 * (args.window // 2 - pad) for s in x0.shape[-2:]),
                      generator=gen).to(device)
    print(f"gaussian filter {args.window}x{args.window} sigma {args.sigma} '{args.padding}' on {list(shape)} "
          f"float32, {device}, forward + backward, {args.repeats} repeats"
          + ("" if cuda else f" ({torch.get_num_threads()} threads)"))

    def row(name: str, t: Tuple[float, Optional[float]], t_ref: Tuple[float, Optional[float]], err: float) -> None:
        k = "" if t[1] is None else f"   kernels {t[1] * 1e3:7.3f} ms x{t_ref[1] / t[1]:5.2f}"
        print(f"  {name:14s} {t[0] * 1e3:8.3f} ms x{t_ref[0] / t[0]:5.2f} vs reference{k}   max |diff| {err:.2e}",
              flush=True)

    ref = t_ref = None
    for name, fn in variants.items():
        x = x0.clone().requires_grad_(True)

        def step(fn=fn, x=x):
            out = fn(x, args.window, args.sigma, pad)
            (gx,) = torch.autograd.grad(out, x, grad)
            return out, gx

        ref, t_ref = _compare_and_time(name, step, ref, t_ref, cuda, args.repeats, row)

    if shape[1] % 5 == 0 and args.padding == "same" and args.window == 11:
        c = shape[1] // 5
        print(f"training SSIM (11x11, 'same') of [{shape[0]},{c},{shape[2]},{shape[3]}], x learns, y fixed: "
              "forward + backward")
        x = x0[:, :c].clone().requires_grad_(True)
        y = x0[:, c:2 * c].clone()
        ref = t_ref = None
        from retinexgs.train.losses import ssim_map
        for name, fn in {"one-call": _ssim_one_call, "torch-split": lambda a, b: ssim(a, b),
                         "fused": lambda a, b: ssim_map(a, b).mean()}.items():
            def step(fn=fn):
                out = fn(x, y)
                (gx,) = torch.autograd.grad(out, x)
                return out, gx

            ref, t_ref = _compare_and_time(name, step, ref, t_ref, cuda, args.repeats, row)
        # A constant of the view that training makes again each step (issue 65: candidates beyond the filter).
        from retinexgs.train.losses import noise_variance
        t = _time_step(lambda: noise_variance(y), cuda, args.repeats)
        print(f"  noise_variance(y) {t[0] * 1e3:8.3f} ms" + ("" if t[1] is None else f"   kernels {t[1] * 1e3:7.3f} ms"))


# ----------------------------------------------------------------------------------------------------- main
def main(argv: List[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n".join(__doc__.splitlines()[2:]))
    sub = ap.add_subparsers(dest="mode", required=True, metavar="MODE")

    p = sub.add_parser("train", help="torch.profiler tables of training steps (GPU)",
                       description=profile_train.__doc__)
    p.add_argument("scene", type=Path)
    p.add_argument("--steps", type=int, default=300, help="warm-up steps before the profile (default 300)")
    p.add_argument("--profile", type=int, default=30, help="profiled steps (default 30)")
    p.add_argument("--rows", type=int, default=40, help="rows of the kernels-by-own-GPU-time table (default 40)")
    p.add_argument("--host", action="store_true",
                   help="also the host's Python by function over --profile more steps (cProfile, unsynchronised)")
    p.add_argument("--slack", type=float, default=0.0, metavar="US",
                   help="also time --profile steps with US µs more work a step on the GPU, then on the host: "
                        "which side bounds the step")
    p.add_argument("--config", action="append", default=[])
    p.add_argument("--set", action="append", default=[], dest="overrides",
                   help="config override, e.g. train.cuda_graphs=false")
    p.set_defaults(fn=profile_train)

    p = sub.add_parser("frame", help="torch.profiler tables of a trained run's frames (GPU)",
                       description=profile_frame.__doc__)
    p.add_argument("run", type=Path, help="a trained run folder")
    p.add_argument("--frames", type=int, default=50)
    p.add_argument("--fused", action="store_true", help="profile the InferenceRenderer instead of model.render")
    p.set_defaults(fn=profile_frame)

    p = sub.add_parser("raster", help="kernel times of the raster bench's forward, ours vs gsplat (GPU)",
                       description=profile_raster.__doc__)
    p.add_argument("--repeats", type=int, default=10)
    p.set_defaults(fn=profile_raster)

    p = sub.add_parser("ops", help="operators per training step, by name and phase (CPU or GPU)",
                       description=OPS_DOC, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", type=Path, nargs="?", help="a scene folder (default: a small synthetic scene)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--profile", type=int, default=30)
    p.add_argument("--config", action="append", default=[])
    p.add_argument("--set", action="append", default=[], dest="overrides")
    p.add_argument("--top", type=int, default=40)
    p.add_argument("--emulate-graphs", action="store_true",
                   help="CPU: run the CUDA-graph path of the step eagerly (its ops show as the phases "
                        "loss_graph and channel_graph, which are 3 graph launches on the GPU)")
    p.add_argument("--size", type=image_size("WxH", "640x480"), default=(96, 72),
                   help="the synthetic scene's views, WxH (default 96x72)")
    p.add_argument("--fused-curves", action="store_true",
                   help="CPU: run the tone curve through its fused kernel, as the GPU does (fused_curve.py)")
    p.add_argument("--traffic", nargs="?", const="phases", choices=("phases", "sites"), default=None,
                   help="also the per-pixel traffic: bytes per pixel per step of the torch ops on tensors of at "
                        "least the largest view's pixel count (a 12 MP step is memory-bound), by phase and op, "
                        "or by the retinexgs line that called each op (--traffic sites)")
    p.set_defaults(fn=count_ops)

    p = sub.add_parser("syncs", help="host reads of tensor values per training step, by call site (CPU or GPU)",
                       description=SYNCS_DOC, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", type=Path, nargs="?", help="a scene folder (default: a small synthetic scene)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    p.add_argument("--steps", type=int, default=300, help="warm-up steps before the counted ones (default 300)")
    p.add_argument("--profile", type=int, default=100, help="counted steps (default 100)")
    p.add_argument("--config", action="append", default=[])
    p.add_argument("--set", action="append", default=[], dest="overrides")
    p.add_argument("--emulate-graphs", action="store_true",
                   help="CPU: run the CUDA-graph path of the step eagerly")
    p.set_defaults(fn=find_syncs)

    p = sub.add_parser("lr3m", help="time LR3M variants on one image (GPU)", description=time_lr3m.__doc__)
    p.add_argument("image", type=Path, help="e.g. a low-light photo of fox-dark")
    p.set_defaults(fn=time_lr3m)

    p = sub.add_parser("ssim", help="SSIM's Gaussian filter, ours vs the 2-D reference, forward + backward",
                       description=time_ssim.__doc__)
    p.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    p.add_argument("--shape", default="1,15,360,640", help="B,C,H,W of the filtered moments (default 1,15,360,640)")
    p.add_argument("--window", type=int, default=11)
    p.add_argument("--sigma", type=float, default=1.5)
    p.add_argument("--padding", choices=["same", "valid"], default="same", help="'same' as training (default)")
    p.add_argument("--repeats", type=int, default=20)
    p.set_defaults(fn=time_ssim)

    args = ap.parse_args(argv)
    if getattr(args, "slack", 0) < 0:
        ap.error(f"--slack must be >= 0 microseconds, got {args.slack:g}")
    return args.fn(args) or 0


if __name__ == "__main__":
    sys.exit(main())
