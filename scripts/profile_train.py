"""Profile RetinexGS training steps on the GPU: where a step's time goes (device machine).

    python scripts/profile_train.py SCENE [--steps 300] [--profile 30] [--config NAME] [--set KEY=VALUE]

Trains ``--steps`` warm-up steps (densification included), then records ``--profile`` steps with
torch.profiler and prints the top operators by CUDA and by CPU time, and the mean wall time per step.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from retinexgs.train.config import load_config
from retinexgs.train.run import open_scene
from retinexgs.train.trainer import Trainer


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", type=Path)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--profile", type=int, default=30)
    ap.add_argument("--config", action="append", default=[])
    ap.add_argument("--set", action="append", default=[], dest="overrides",
                    help="config override, e.g. train.cuda_graphs=false")
    args = ap.parse_args()
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


if __name__ == "__main__":
    main()
