"""Profile the full enhanced render of a trained run on the GPU: operators by CUDA and CPU time, launches per frame.

    python scripts/profile_frame.py RUN [--frames 50] [--fused]

``--fused`` profiles the InferenceRenderer (fused colour kernel + CUDA-graph enhancement: what render, export and
the viewer use) instead of ``model.render``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--fused", action="store_true", help="profile the InferenceRenderer instead of model.render")
    args = ap.parse_args()
    from retinexgs.model.inference import InferenceRenderer
    from retinexgs.train.run import load_run
    from retinexgs.train.trainer import active_sh_degree, view_camera

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


if __name__ == "__main__":
    main()
