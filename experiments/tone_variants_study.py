"""Score highlight roll-offs off the GPU (issue 53: where a warm scene's cast comes from) on dumps of trained runs
(experiments/white_balance_dump.py): the test views' linear light encoded with each roll-off, then the sRGB curve, and
scored against the truth with eval's colour error (ΔE of the average colours after GT-mean), GT-mean PSNR and SSIM,
at half resolution.

    python experiments/tone_variants_study.py DUMP.npz... --data DATA_ROOT [--set data.downscale=2]

Roll-offs: per-channel (the renderer's: each channel through the shoulder), clip (no shoulder), luminance (the
Rec. 709 luminance through the shoulder, the three channels scaled alike) and max-RGB (the brightest channel through
the shoulder, the three scaled alike: hue and saturation kept). A dump's scene is found by its file name's first
part, as in experiments/white_balance_study.py.
"""
from __future__ import annotations

import sys
from typing import Callable, Dict

import torch

from retinexgs.model.tone import highlight_shoulder
from white_balance_study import dump_study_args, load_dump, score_test_views  # scripts/ is on sys.path when run as a script

_LUMA = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)


def _scaled(v: torch.Tensor, drive: torch.Tensor, knee: float) -> torch.Tensor:
    drive = drive.clamp_min(1e-9)
    return v * highlight_shoulder(drive, knee) / drive


ROLL_OFFS: Dict[str, Callable[[torch.Tensor, float], torch.Tensor]] = {
    "per-channel": highlight_shoulder,
    "clip": lambda v, knee: v,
    "luminance": lambda v, knee: _scaled(v, (v * _LUMA).sum(-1, keepdim=True), knee),
    "max-rgb": lambda v, knee: _scaled(v, v.amax(-1, keepdim=True), knee),
}


def main(argv=None) -> int:
    args, cfg = dump_study_args(__doc__, argv)
    print("run | " + " | ".join(f"{n}: ΔE, GT-mean PSNR, SSIM" for n in ROLL_OFFS))
    for dump in args.dumps:
        d, truth, knee = load_dump(dump, args.data, cfg)
        cells = []
        for roll in ROLL_OFFS.values():
            de, ps, ss = score_test_views(d, truth, lambda v, roll=roll: roll(v, knee), with_ssim=True)
            cells.append(f"{de:.2f}, {ps:.2f}, {ss:.3f}")
        print(f"{dump.stem} | " + " | ".join(cells))
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
