"""How far multi-view averaging alone can take a raw capture's SSIM: each test view's own raw data (demosaiced,
linear, unclipped, as training reads it, ``View.load_target``) is k·truth + noise. The noise's variance is measured
per channel against the level (var = a·m + b, least squares over 20 level bins); n aligned views averaged would
leave var / n. Printed: the GT-mean SSIM of srgb((k·t + N(0, var / n)) / k) against the truth, mean over the test
views, for each n. A trained run above these figures has gone past averaging (its spatial priors).

    python experiments/raw_averaging_bound.py SCENE [--views 1,11,25] [--seed 0]

SCENE: a raw-ladder capture with normal-light truths (``python -m retinexgs.bench quality --raw-ladder LEVEL
--no-train``, its ``SCENE@LEVEL-raw`` folder). The noise is taken as independent from pixel to pixel, which the
demosaicing makes it not quite: a reference, not a proof.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear, srgb_to_linear_extended
from retinexgs.evaluate.metrics import gt_mean_align, ssim_metric
from retinexgs.run.config import load_config
from retinexgs.run.folder import open_scene


def noise_fit(level: torch.Tensor, residual: torch.Tensor, bins: int = 20) -> tuple:
    """(a, b) of var = a·level + b for one channel, by least squares over ``bins`` equal-count level bins."""
    m, r = level.flatten(), residual.flatten()
    edges = torch.quantile(m, torch.linspace(0, 1, bins + 1, dtype=torch.float64))
    xs, vs = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (m >= lo) & (m < hi)
        if int(sel.sum()) > 200:
            xs.append(float(m[sel].mean()))
            vs.append(float(r[sel].var()))
    a, b = np.linalg.lstsq(np.stack([xs, np.ones(len(xs))], 1), np.array(vs), rcond=None)[0]
    return max(float(a), 0.0), max(float(b), 1e-12)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scene", type=Path)
    p.add_argument("--views", default="1,11,25", help="numbers of aligned views averaged")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    ns = [int(x) for x in args.views.split(",")]
    scene = open_scene(args.scene, load_config())
    if not scene.raw:
        raise SystemExit(f"{args.scene} is not a camera raw scene")
    gen = torch.Generator().manual_seed(args.seed)
    scores = {n: [] for n in ns}
    for v in scene.test:
        if v.paired_path is None:
            continue
        y = srgb_to_linear_extended(v.load_target().double())
        truth = v.paired_image.double()
        t = srgb_to_linear(truth)
        k = (y * t).sum((0, 1)) / (t * t).sum((0, 1))  # the capture's exposure, per channel
        m = k * t
        ab = [noise_fit(m[..., c], (y - m)[..., c]) for c in range(3)]
        var = torch.stack([a * m[..., c].clamp_min(0) + b for c, (a, b) in enumerate(ab)], -1)
        for n in ns:
            noisy = m + torch.randn(m.shape, generator=gen, dtype=torch.float64) * (var / n).sqrt()
            scores[n].append(ssim_metric(gt_mean_align(linear_to_srgb(noisy / k), truth), truth))
        print(f"{v.name}: exposure {[round(float(x), 4) for x in k]}, noise a·m + b per channel "
              f"{[(float(f'{a:.3g}'), float(f'{b:.3g}')) for a, b in ab]}", flush=True)
    print(f"{args.scene} ({len(scene.train)} training views): GT-mean SSIM of n views averaged: "
          + ", ".join(f"n = {n}: {np.mean(s):.3f}" for n, s in scores.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
