"""L_enhance through its kernels (retinexgs/train/fused_enhance.py) against the torch composition, forward + backward,
at the 12 MP raw scene's training sizes: ms each and their ratio, one process, one GPU (issue 65: it lifted the
kernels' bound of 0.26 MP, ``fused_enhance.MAX_PIXELS`` until session 27;
experiments/notes/2026-11-30-fused-enhance.md).

    python experiments/enhance_loss_probe.py [--sizes 360x640,750x1000,1500x2000,3000x4000] [--iters 20]

The model is the default configuration's on a tiny demo scene (its EnhancementNet and exposure tone are what
L_enhance uses); R̂ and L̂ are random maps of each size. Each iteration: the objective's terms, their backward into
the EnhancementNet, a synchronize; the median of ``--iters`` after 3 warm-ups, each path alternately. The terms of
the two paths are printed side by side (they must agree).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from retinexgs.data import load_scene  # noqa: E402
from retinexgs.demo.synthetic import make_demo_scene  # noqa: E402
from retinexgs.run.config import load_config  # noqa: E402
from retinexgs.train import fused_enhance  # noqa: E402
from retinexgs.train.objective import enhancement_objective  # noqa: E402
from retinexgs.train.trainer import Trainer  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="360x640,750x1000,1500x2000,3000x4000")
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument("--device", default="cuda", help="cuda, or cpu (a smoke test: the CPU kernels, the curve fused)")
    args = ap.parse_args()
    dev = torch.device(args.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        print("needs a CUDA GPU (or --device cpu)", file=sys.stderr)
        return 2
    if dev.type == "cpu":  # the kernels' path is the GPU's; on the CPU only to check that this script runs
        from retinexgs.model.tones import fused_curve
        fused_curve.runs_fused = lambda x: True
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    root = Path(tempfile.mkdtemp(prefix="enhance_probe_"))
    scene = make_demo_scene(root / "demo", n_train=3, n_test=1, width=44, height=30, n_points=300)
    cfg = load_config([], ["steps=4", "log.tensorboard=false", "model.max_init_points=300",
                           "decomposer.method=lime"])
    tr = Trainer(cfg, load_scene(scene), root / "run", args.device, progress=False, log=lambda s: None)
    model, c = tr.model, tr.cfg.loss
    with torch.no_grad():  # a net that answers its input (its output layer starts at zero weights)
        model.enhancement.out.weight.normal_(0, 0.3)
    real_applies = fused_enhance.applies
    print(f"{'size':>11}  {'MP':>5}  {'kernels ms':>10}  {'torch ms':>9}  {'ratio':>6}  terms (kernels | torch)")
    for spec in args.sizes.split(","):
        try:
            H, W = (int(v) for v in spec.split("x"))
        except ValueError:
            print(f"--sizes: {spec!r} is not HxW (e.g. 360x640)", file=sys.stderr)
            return 2
        g = torch.Generator(device=dev).manual_seed(0)
        R = torch.rand((H, W, 3), device=dev, generator=g) * 0.8 + 0.1
        L = torch.rand((H, W, 3), device=dev, generator=g) * 0.05 + 0.01
        S = (R * L + 0.002 * torch.randn((H, W, 3), device=dev, generator=g)).clamp_min(0)
        S_b = S.permute(2, 0, 1).unsqueeze(0)
        times = {True: [], False: []}
        terms = {}
        for i in range(3 + args.iters):
            for fused in (True, False):
                fused_enhance.applies = (real_applies if fused else (lambda *a, **k: False))
                assert fused_enhance.applies(model, c, R) == fused, "the kernels' path does not apply here"
                model.enhancement.zero_grad(set_to_none=True)
                sync()
                t = time.perf_counter()
                total, t_terms = enhancement_objective(model, c, R, L, S_b)
                total.backward()
                sync()
                if i >= 3:
                    times[fused].append((time.perf_counter() - t) * 1e3)
                terms[fused] = [float(t_terms[k].detach()) for k in ("spa", "exp", "col")]
        fused_enhance.applies = real_applies
        k, r = statistics.median(times[True]), statistics.median(times[False])
        fmt = lambda v: " ".join(f"{x:.5g}" for x in v)  # noqa: E731
        print(f"{spec:>11}  {H * W / 1e6:5.2f}  {k:10.3f}  {r:9.3f}  {k / r:6.3f}  {fmt(terms[True])} | "
              f"{fmt(terms[False])}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
