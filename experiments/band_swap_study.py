"""Is a trained run's SSIM lost in its luma or its chroma, its fine detail or its coarse? (issue 64)

For each test view with a normal-light truth, the enhanced render (GT-mean aligned, as `eval`) is scored as it is
and with one part replaced by the truth's, by the evaluation SSIM over the whole view and the truth's dark, mid and
bright thirds (:func:`dark_region_study.region_ssim`). The parts: the coarse image (a Gaussian blur of σ ``--sigma``
px) or the detail under it; the luma (Rec. 601 grey) or the chroma (the image less its luma); the coarse chroma. A
part whose replacement lifts the score most is where the run loses it.

    python experiments/band_swap_study.py RUN [--sigma 4] [--device cpu]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List

import torch
import torch.nn.functional as F

from retinexgs.evaluate.metrics import gt_mean_align
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, render_function

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dark_region_study import region_ssim  # noqa: E402

_GREY = (0.299, 0.587, 0.114)


def blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """[H,W,C] blurred by a separable Gaussian of ``sigma`` px (3σ reach, edges replicated)."""
    r = max(1, int(3 * sigma))
    t = torch.arange(-r, r + 1, dtype=torch.float32)
    k = torch.exp(-t ** 2 / (2 * sigma ** 2))
    k = k / k.sum()
    y = x.permute(2, 0, 1)[:, None]
    y = F.conv2d(F.pad(y, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    y = F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return y[:, 0].permute(1, 2, 0)


def swaps(a: torch.Tensor, b: torch.Tensor, sigma: float) -> Dict[str, torch.Tensor]:
    """The render ``a`` and its variants with one part of the truth ``b`` put in (each [H,W,3] in [0, 1])."""
    g = a.new_tensor(_GREY)
    ya, yb = (a * g).sum(-1, keepdim=True), (b * g).sum(-1, keepdim=True)
    ca, cb = a - ya, b - yb
    alo, blo = blur(a, sigma), blur(b, sigma)
    return {"render": a,
            "truth's coarse": a - alo + blo,
            "truth's detail": alo + b - blo,
            "truth's luma": ca + yb,
            "truth's chroma": cb + ya,
            "truth's coarse chroma": ya + ca - blur(ca, sigma) + blur(cb, sigma)}


def main(argv: List[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--sigma", type=float, default=4.0)
    ap.add_argument("--device", default=None)
    args = ap.parse_args(argv)
    cfg, scene, model, step = load_run(args.run, args.device)
    render = render_function(model, cfg, active_sh_degree(cfg, step))
    rows: Dict[str, List[List[float]]] = {}
    for view in scene.test:
        truth = view.paired_image
        if truth is None:
            continue
        b = truth.cpu().float()
        a = gt_mean_align(render(view)["rgb"].clamp(0, 1).cpu().float(), b).float()
        for name, img in swaps(a, b, args.sigma).items():
            rows.setdefault(name, []).append(region_ssim(img.clamp(0, 1), b))
    if not rows:
        print("no test view with a normal-light truth")
        return 1
    print(f"run {args.run} (step {step}): SSIM whole / dark / mid / bright third, σ {args.sigma} px, "
          f"mean over {len(rows['render'])} test views")
    for name, vals in rows.items():
        m = [sum(v[i] for v in vals) / len(vals) for i in range(4)]
        print(f"  {name:22s} " + " / ".join(f"{x:.3f}" for x in m))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
