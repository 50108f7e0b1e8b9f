"""What the tone alone costs a scene's colour error: each test view's normal-light truth sent through the render's
tone (linear light times an exposure factor, the highlight shoulder at a knee, the sRGB curve and its clip) and
scored against itself with eval's colour error (ΔE after GT-mean), for a grid of exposures and knees. A render whose
light were exactly the truth's would score these figures (:func:`retinexgs.evaluate.metrics.tone_colour_floor`);
eval writes the one at each run's own exposure and knee as ``delta_e_tone_floor``.

    python experiments/tone_colour_floor.py SCENE... [--exposures 0.7,0.85,1,1.5] [--knees 0.5,1] [--downscale 2]

SCENE: a folder with transforms_test.json and high/ (the normal-light photos), e.g. ../shared/data/strecha/castlep30-dark.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from retinexgs.evaluate.metrics import tone_colour_floor


def _truths(scene: Path, downscale: int):
    frames = json.loads((scene / "transforms_test.json").read_text())["frames"]
    for frame in frames:
        stem = Path(frame["file_path"]).stem
        hits = sorted((scene / "high").glob(stem + ".*"))
        if not hits:
            raise SystemExit(f"{scene}: no normal-light photo high/{stem}.* for test view {stem}")
        img = Image.open(hits[0]).convert("RGB")
        if downscale > 1:
            img = img.reduce(downscale)
        yield stem, torch.from_numpy(np.asarray(img, dtype=np.float64) / 255.0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenes", nargs="+", type=Path)
    p.add_argument("--exposures", default="0.7,0.85,1,1.5", help="exposure factors, render / truth in linear light")
    p.add_argument("--knees", default="0.5,1", help="highlight knees (1: the clip)")
    p.add_argument("--downscale", type=int, default=2, help="integer reduction of the photos first (speed)")
    args = p.parse_args(argv)
    exposures = [float(x) for x in args.exposures.split(",")]
    knees = [float(x) for x in args.knees.split(",")]
    cols = [(e, k) for e in exposures for k in knees]
    for scene in args.scenes:
        print(f"{scene}: ΔE of the truth through the tone | " + " | ".join(f"x{e:g} knee {k:g}" for e, k in cols)
              + " | share of pixels with a channel at 255")
        table = []
        for stem, y in _truths(scene, args.downscale):
            row = [tone_colour_floor(y, k, e) for e, k in cols]
            clipped = float((y >= 1.0).any(-1).double().mean())
            table.append(row)
            print(f"  {stem} | " + " | ".join(f"{v:.2f}" for v in row) + f" | {clipped:.3f}")
        print("  mean | " + " | ".join(f"{v:.2f}" for v in np.mean(table, axis=0)))
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
