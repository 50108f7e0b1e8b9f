"""Per-pixel memory traffic of one training step's torch operators, by the retinexgs line that called each one.

A 12 MP step is memory-bound: every elementwise operator on a full-size tensor reads and writes ~100 MB. This
counts, for one step on the CPU (the operators are the GPU's too; the project's own kernels are not counted), the
bytes each operator reads and writes in tensors at least as large as the view, divided by the view's pixels, and
attributes them to the innermost retinexgs frame on the Python stack (the graphed losses' backward shows as
``train/graphs.py`` ``_step``). Usage (a synthetic scene of 6 views; any config overrides after the size):

    python experiments/step_traffic_census.py 640x480 [KEY=VALUE ...]

Results: experiments/notes/2026-11-29-redenoise-gpu-step-launches.md §5.
"""
import argparse
import collections
import sys
import tempfile
import traceback
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import profiling  # noqa: E402  (scripts/profiling.py: the warm trainer and the metadata-only operators)


class Census(TorchDispatchMode):
    """Bytes per (call site, operator) of the operators whose largest tensor has >= ``min_numel`` elements."""

    def __init__(self, min_numel: int) -> None:
        super().__init__()
        self.min_numel = min_numel
        self.traffic: collections.Counter = collections.Counter()
        self.by_site: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = profiling._op_name(func)
        if name in profiling.METADATA or name.startswith("profiler."):
            return out
        tensors = [t for t in torch.utils._pytree.tree_leaves((args, kwargs, out)) if isinstance(t, torch.Tensor)]
        if max((t.numel() for t in tensors), default=0) >= self.min_numel:
            site = "?"
            for frame in reversed(traceback.extract_stack()[:-1]):
                if "/retinexgs/" in frame.filename:
                    site = f"{frame.filename.split('/retinexgs/')[1]}:{frame.lineno} {frame.name}"
                    break
            size = sum(t.numel() * t.element_size() for t in tensors)
            self.traffic[(site, name)] += size
            self.by_site[site] += size
        return out


def main() -> None:
    size = sys.argv[1] if len(sys.argv) > 1 else "640x480"
    args = argparse.Namespace(scene=None, device="cpu", steps=4, config=[], overrides=sys.argv[2:],
                              emulate_graphs=True, size=size)
    with tempfile.TemporaryDirectory() as tmp:
        trainer, _ = profiling._warm_trainer(args, tmp)
        pixels = max(v.camera.width * v.camera.height for v in trainer.views)
        census = Census(pixels)
        with census:
            trainer.train(stop_after=1)
    print(f"{size}: {sum(census.traffic.values()) / pixels:.0f} B/px a step (torch operators on view-sized tensors)")
    for site, b in census.by_site.most_common(40):
        print(f"{b / pixels:8.1f}  {site}")
    print("--- by (site, operator)")
    for (site, name), b in census.traffic.most_common(40):
        print(f"{b / pixels:8.1f}  {name:<18} {site}")


if __name__ == "__main__":
    main()
