"""Count the operators of RetinexGS training steps, per step and by name (a proxy for kernel launches).

    python scripts/count_step_ops.py [SCENE] [--device cpu|cuda] [--steps 300] [--profile 30]
                                     [--config NAME] [--set KEY=VALUE] [--top 40]

Without SCENE a small synthetic scene is generated (96x72, 4000 points). Trains ``--steps`` warm-up steps
with the enhancement losses switched on half way (as scripts/profile_train.py does), then counts the
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
from __future__ import annotations

import argparse
import collections
import tempfile
from pathlib import Path
from typing import Dict, List

import torch
from torch.utils._python_dispatch import TorchDispatchMode

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


class OpCounter(TorchDispatchMode):
    """Counts every operator that reaches a backend, by name and by the trainer's current phase."""

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", type=Path, nargs="?")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--profile", type=int, default=30)
    ap.add_argument("--config", action="append", default=[])
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--emulate-graphs", action="store_true",
                    help="CPU: run the CUDA-graph path of the step eagerly (its ops show as the phases "
                         "loss_graph and channel_graph, which are 3 graph launches on the GPU)")
    args = ap.parse_args()

    from retinexgs.render import _backend
    from retinexgs.train.config import load_config
    from retinexgs.train.run import open_scene
    from retinexgs.train.trainer import Trainer

    cuda = args.device.startswith("cuda")
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
        tr = Trainer(cfg, scene, run, args.device, progress=False, log=lambda s: None, **extra)
        tr.train(stop_after=args.steps)
        k = _backend.kernels()
        kernel_calls = count_calls(k, [n for n in dir(k) if not n.startswith("_") and callable(getattr(k, n))])
        graph_calls = count_calls(torch.cuda.CUDAGraph, ["replay"]) if cuda else {}
        # Reads of tensor values by the host (a sync on the GPU) and tensors built from host numbers (a
        # host->device copy on the GPU), whatever the device.
        counter = OpCounter()
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
        print(f"steps {first}..{tr.step} on {args.device}, {len(tr.model.gaussians)} Gaussians, "
              f"config {args.config or ['default']} {args.overrides}, "
              f"cuda_graphs={cfg['train']['cuda_graphs'] if 'train' in cfg else 'n/a'}")
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
        print(f"host reads / tensors from host numbers per step: "
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


if __name__ == "__main__":
    main()
