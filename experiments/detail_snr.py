"""How much of a scene's fine detail could a night capture's views carry, averaged perfectly? (issue 64)

For each test view's normal-light truth (``high/``), by the truth's grey thirds as in ``dark_region_study.py``: the
mean linear luminance and the standard deviation of its detail under a Gaussian blur of σ ``--sigma`` px, both in the
electrons a sample of the raw ladder's sensor collects (``--exposure`` × ``--full-well`` per unit of linear light;
the ladder's 1000 e⁻ rung: 0.05 × 1000), against one view's noise sqrt(e + read²) and that noise averaged over
``--views`` views (fox-dark: 35 views see a point). The demosaic and the colour matrix, which add noise, are left out:
the SNRs are upper bounds.

    python experiments/detail_snr.py SCENE [--views 35] [--sigma 2] [--exposure 0.05] [--full-well 1000] [--read-noise 6]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import List

import numpy as np
import torch
from PIL import Image

from retinexgs.data.srgb import srgb_to_linear

sys.path.insert(0, str(Path(__file__).resolve().parent))
from band_swap_study import blur  # noqa: E402

_GREY = (0.299, 0.587, 0.114)
_LUMA = (0.2126, 0.7152, 0.0722)


def main(argv: List[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--views", type=int, default=35)
    ap.add_argument("--sigma", type=float, default=2.0)
    ap.add_argument("--exposure", type=float, default=0.05)
    ap.add_argument("--full-well", type=float, default=1000.0)
    ap.add_argument("--read-noise", type=float, default=6.0)
    args = ap.parse_args(argv)
    split = args.scene / "transforms_test.json"
    if not split.is_file():
        raise SystemExit(f"{args.scene} has no transforms_test.json (a scene with normal-light truths in high/)")
    frames = json.loads(split.read_text())["frames"]
    scale = args.exposure * args.full_well
    rows = {"dark": [], "mid": [], "bright": []}
    for f in frames:
        path = args.scene / "high" / Path(f["file_path"]).name
        if not path.suffix:
            path = path.with_suffix(".jpg")
        im = torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0)
        grey = (im * im.new_tensor(_GREY)).sum(-1)
        lo, hi = torch.quantile(grey.flatten(), grey.new_tensor([1 / 3, 2 / 3]))
        y = (srgb_to_linear(im) * im.new_tensor(_LUMA)).sum(-1, keepdim=True)
        detail = (y - blur(y, args.sigma))[..., 0]
        for name, m in (("dark", grey < lo), ("mid", (grey >= lo) & (grey <= hi)), ("bright", grey > hi)):
            e, d = scale * float(y[..., 0][m].mean()), scale * float(detail[m].std())
            rows[name].append((e, d, (e + args.read_noise ** 2) ** 0.5))
    print(f"{args.scene} ({len(frames)} test views; {scale:g} e- per unit of linear light, read noise "
          f"{args.read_noise:g} e-, detail under σ {args.sigma:g} px)")
    for name, vals in rows.items():
        e, d, n = np.mean(np.array(vals), axis=0)
        print(f"  {name:6s} mean {e:5.1f} e-, detail σ {d:4.2f} e-, noise a view {n:4.2f} e-: detail SNR one view "
              f"{d / n:.2f}, {args.views} views averaged {d / n * args.views ** 0.5:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
