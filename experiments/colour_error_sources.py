"""Where a trained run's colour error comes from (issues 52 and 53), off the GPU, on dumps of trained runs
(experiments/white_balance_dump.py). For each run, ΔE of average colours (CIELAB 1976), each view's output scaled to
its truth's mean luminance:

- fit: the training views' linear light against their truths: what the reconstruction left;
- novel: the test views' linear light against theirs: what the novel views add;
- rendered: the test views as eval scores them (the run's shoulder, the sRGB curve, GT-mean);
- at the truth's exposure: the test views' light scaled so that its mean luminance is the truth's before the
  shoulder, then as rendered (how much the exposure the meter chose adds through the tone's nonlinearity),
  with the factor output / truth.

    python experiments/colour_error_sources.py DUMP.npz... --data DATA_ROOT [--set data.downscale=2]
"""
from __future__ import annotations

import sys
from typing import Dict, List

import numpy as np
import torch

from retinexgs.data.srgb import linear_to_srgb, linear_to_srgb_extended, srgb_to_linear
from retinexgs.evaluate.metrics import colour_error, mean_colour_lab
from retinexgs.model.tone import highlight_shoulder
from retinexgs.run.folder import open_scene
from white_balance_study import _find_scene, _half_srgb, dump_study_args  # scripts/ is on sys.path when run as a script

_LUMA = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)


def _lab_of(light: torch.Tensor) -> np.ndarray:
    return np.array(mean_colour_lab(linear_to_srgb_extended(light.reshape(-1, 3).mean(0).reshape(1, 1, 3))))


def mean_colour_error(light: torch.Tensor, truth_light: torch.Tensor) -> np.ndarray:
    """(ΔE, ΔL*, Δa*, Δb*) of the average colour of ``light`` scaled to ``truth_light``'s mean luminance."""
    s = float((truth_light * _LUMA).sum(-1).mean() / (light * _LUMA).sum(-1).mean().clamp_min(1e-12))
    d = _lab_of(light * s) - _lab_of(truth_light)
    return np.array([np.linalg.norm(d), *d])


def main(argv=None) -> int:
    args, cfg = dump_study_args(__doc__, argv)
    print("run | fit ΔE (Δa*, Δb*) | novel ΔE (Δa*, Δb*) | rendered ΔE | exposure output/truth | ΔE at the truth's exposure")
    for dump in args.dumps:
        d = np.load(dump)
        scene = open_scene(_find_scene(args.data, dump.stem.split("_")[0]), cfg)
        views = {v.name: v for v in list(scene.train) + list(scene.test) if v.paired_path is not None}
        knee = float(d["knee"])
        rows: Dict[str, List] = {"train": [], "test": [], "rendered": [], "ratio": [], "oracle": []}
        for key in d.files:
            split, _, name = key.partition("/")
            if split not in ("train", "test") or name not in views:
                continue
            gt = _half_srgb(views[name].paired_image)
            light = torch.from_numpy(d[key].astype(np.float64))
            hh, ww = min(light.shape[0], gt.shape[0]), min(light.shape[1], gt.shape[1])
            light, gt = light[:hh, :ww], gt[:hh, :ww]
            truth_light = srgb_to_linear(gt)
            rows[split].append(mean_colour_error(light, truth_light))
            if split == "test":
                rows["rendered"].append(colour_error(linear_to_srgb(highlight_shoulder(light, knee)).clamp(0, 1), gt))
                r = float((light * _LUMA).sum(-1).mean() / (truth_light * _LUMA).sum(-1).mean())
                rows["ratio"].append(r)
                at_truth = linear_to_srgb(highlight_shoulder(light / r, knee)).clamp(0, 1)
                rows["oracle"].append(colour_error(at_truth, gt))
        fit, novel = np.mean(rows["train"], axis=0), np.mean(rows["test"], axis=0)
        print(f"{dump.stem} | {fit[0]:.2f} ({fit[2]:+.2f}, {fit[3]:+.2f}) | {novel[0]:.2f} ({novel[2]:+.2f}, {novel[3]:+.2f})"
              f" | {np.mean(rows['rendered']):.2f} | x{np.exp(np.mean(np.log(rows['ratio']))):.2f}"
              f" | {np.mean(rows['oracle']):.2f}")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
