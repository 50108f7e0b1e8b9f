"""Where the time goes: profiles of training steps, frames and the rasterizer, operator counts, LR3M timings.

    python scripts/profiling.py train SCENE [--steps 300] [--profile 30] [--config NAME] [--set KEY=VALUE]
    python scripts/profiling.py frame RUN [--frames 50] [--fused]
    python scripts/profiling.py raster [--repeats 10]
    python scripts/profiling.py ops [SCENE] [--device cpu|cuda] [--steps 300] [--profile 30] [--emulate-graphs]
    python scripts/profiling.py lr3m IMAGE

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
- ``lr3m`` (GPU): times LR3M variants on one image; prints the fastest setting as ``--set`` overrides.

``scripts/device.sh speed`` runs the GPU modes on the device machine (its stages profile, fprofile, rprofile, lr3m).
"""
from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List

import torch


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
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        tr.train(stop_after=args.profile)
        torch.cuda.synchronize()
        print(f"{(time.perf_counter() - t0) / args.profile * 1e3:.2f} ms per step (unprofiled), "
              f"{len(tr.model.gaussians)} Gaussians")
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
        print(table.table(sort_by="cpu_time_total", row_limit=20))


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


def _op_counter():
    """A TorchDispatchMode that counts every operator reaching a backend, by name and by the trainer's phase
    (built on first use: the dispatch-mode import is private torch API, needed by ``ops`` alone)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class OpCounter(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
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
            return func(*args, **kwargs)

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


def count_ops(args: argparse.Namespace) -> None:
    """Operators per training step as the backends see them (CPU or GPU)."""
    from retinexgs.render import _backend
    from retinexgs.run.config import load_config
    from retinexgs.run.folder import open_scene
    from retinexgs.train.trainer import Trainer

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    cuda = device.startswith("cuda")
    with tempfile.TemporaryDirectory() as tmp:
        scene_path = args.scene
        if scene_path is None:
            from retinexgs.demo.synthetic import make_demo_scene
            scene_path = make_demo_scene(Path(tmp) / "scene", n_train=6, n_test=1, width=96, height=72,
                                         n_points=4000)
        cfg = load_config(args.config, [f"loss.enhance_from={args.steps // 2}"] + args.overrides)
        scene = open_scene(scene_path, cfg)
        run = Path(tmp) / "run"
        run.mkdir()
        extra = {"emulate_graphs": True} if args.emulate_graphs else {}  # (older trainers lack the argument)
        tr = Trainer(cfg, scene, run, device, progress=False, log=lambda s: None, **extra)
        tr.train(stop_after=args.steps)
        k = _backend.kernels()
        kernel_calls = count_calls(k, [n for n in dir(k) if not n.startswith("_") and callable(getattr(k, n))])
        graph_calls = count_calls(torch.cuda.CUDAGraph, ["replay"]) if cuda else {}
        # Reads of tensor values by the host (a sync on the GPU) and tensors built from host numbers (a
        # host->device copy on the GPU), whatever the device.
        counter = _op_counter()
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
              f"cuda_graphs={cfg.train.cuda_graphs}")
        print(f"aten ops per step (all):          {sum(counter.ops.values()) / n:8.1f}")
        print(f"kernel ops per step (no views):   {sum(kernel_ops.values()) / n - optim / n:8.1f}"
              f"  (+ {optim / n:.1f} in the optimiser step: one fused kernel per group on the GPU)")
        if graphed:
            print(f"kernel ops per step outside graphs: {(sum(kernel_ops.values()) - optim - graphed) / n:8.1f}"
                  f"  (+ {graphed / n:.1f} inside the phases *_graph: 3 graph launches on the GPU)")
        print("  by phase: " + ", ".join(f"{p[5:]} {c / n:.1f}" for p, c in sorted(counter.phases.items())))
        print(f"retinexgs._C calls per step:      {sum(kernel_calls.values()) / n:8.1f}  "
              + ", ".join(f"{k} {v / n:.1f}" for k, v in sorted(kernel_calls.items())))
        print(f"host syncs per step: {counter.syncs / n:.2f} item/bool/int (optimiser apart), "
              f"{counter.d2h / n:.2f} device->host copies (+ 1 for binning's pair count on CUDA)")
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
        rows = sorted(kernel_ops.items(), key=lambda kv: -kv[1])[: args.top]
        print(f"\ntop {len(rows)} kernel ops per step (optimiser included):")
        for name, count in rows:
            print(f"  {count / n:8.2f}  {name}")


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
    p.set_defaults(fn=count_ops)

    p = sub.add_parser("lr3m", help="time LR3M variants on one image (GPU)", description=time_lr3m.__doc__)
    p.add_argument("image", type=Path, help="e.g. a low-light photo of fox-dark")
    p.set_defaults(fn=time_lr3m)

    args = ap.parse_args(argv)
    args.fn(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
