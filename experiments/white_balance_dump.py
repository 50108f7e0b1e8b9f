"""Dump what a render-time white-balance estimator sees of trained runs (issue 53), so that estimators can be
compared off the GPU: per run one compressed ``.npz`` with, as float16,

- ``test/<view>``: the test views' enhanced linear light as trained (:func:`~retinexgs.run.render.enhanced_linear`,
  before any balance, the shoulder and the sRGB curve), [H/2,W/2,3] (2×2 means in linear light: the colour error
  is a mean colour, and half the size lets a dozen runs come back from the GPU machine);
- ``train/<view>``: up to ``--train-views`` training views (evenly spaced), the same light at half resolution;
- ``knee``: the run's highlight shoulder (1: none).

    python experiments/white_balance_dump.py RUN... --out DIR [--train-views 10] [--device cuda]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, render_function


def _half(x: torch.Tensor) -> np.ndarray:
    h, w = x.shape[0] // 2 * 2, x.shape[1] // 2 * 2
    x = x[:h, :w].reshape(h // 2, 2, w // 2, 2, 3).mean(dim=(1, 3))
    return x.cpu().numpy().astype(np.float16)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--train-views", type=int, default=10)
    p.add_argument("--name-from-parents", type=int, default=0,
                   help="name each file after the run folder's last N path parts (runs of one name in several folders)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for run in args.runs:
        cfg, scene, model, step = load_run(run, args.device)
        fn = render_function(model, cfg, active_sh_degree(cfg, step), linear=True)
        arrays = {"knee": np.float32(getattr(model, "shoulder", 1.0))}
        for v in scene.test:
            arrays[f"test/{v.name}"] = _half(fn(v)["rgb_linear"])
        train = list(scene.train)
        for v in train[:: max(1, -(-len(train) // args.train_views))]:
            arrays[f"train/{v.name}"] = _half(fn(v)["rgb_linear"])
        name = args.name_from_parents and "_".join(run.parts[-args.name_from_parents:]) or run.name
        np.savez_compressed(args.out / f"{name}.npz", **arrays)
        print(f"{run}: {len(arrays)} arrays -> {args.out / (name + '.npz')}")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
