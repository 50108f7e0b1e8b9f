"""Is the 3D model's own render a better pilot for denoising a night view than the view alone? (issue 64 item 1)

The issue's premise: BM3D's second stage (a Wiener filter whose gains come from a pilot estimate) is only as good as
its pilot, and a render of the trained model, which averages every view that saw the scene, is a far better pilot
than a single-view denoiser's output. This study measures that premise on a trained run before any training code
changes: for the first ``--views`` training views it scores, against the view's normal-light truth (GT-mean
aligned, as `eval`), the candidate targets a denoising loop could train on:

- ``noisy``: the view's light as training reads it (a raw view unclipped);
- ``today``: the denoiser of ``decomposer.denoise`` (the run's, or ``--method``) on that view alone;
- ``render``: the model's R̂∘L̂ at that view (the pilot itself);
- ``wiener``: the view filtered with Wiener gains from the pilot, per 8×8 DCT block of the variance-stabilised
  luma/chroma (the generalised Anscombe transform of ``retinexgs.retinex.denoise``: unit noise, so a coefficient's
  gain is P² / (P² + 1)), overlapping blocks averaged;
- ``wiener-luma``: the Wiener luma with today's chroma (the render's chroma carries its colour blotches).

Each candidate's linear light is exposed by one gain (its mean luma to 0.18) and encoded as sRGB before the GT-mean
alignment, so every candidate is treated alike. Columns: PSNR / SSIM / chroma_noise (1 = the truth's colour
structure), mean over the views.

    python experiments/pilot_wiener_study.py RUN [--views 8] [--device cuda] [--method chroma] [--block 8]
"""
from __future__ import annotations

import argparse
import sys
from typing import Dict, List

import torch

from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear, srgb_to_linear_extended
from retinexgs.evaluate.metrics import chroma_noise, gt_mean_align, psnr, ssim_metric
from retinexgs.retinex.denoise import denoise_linear, pilot_wiener
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, render_function
from retinexgs.train.view_setup import denoise_spec


def exposed_srgb(lin: torch.Tensor) -> torch.Tensor:
    """sRGB of ``lin`` [H,W,3] with its mean luma exposed to 0.18 (one gain), clipped."""
    luma = (lin.clamp_min(0) * lin.new_tensor([0.2126, 0.7152, 0.0722])).sum(-1).mean()
    return linear_to_srgb((lin * (0.18 / luma.clamp_min(1e-8))).clamp(0, 1))


def score(rows: Dict[str, List[tuple]], name: str, lin: torch.Tensor, truth: torch.Tensor) -> None:
    """Append candidate ``name``'s (PSNR, SSIM, chroma_noise) against ``truth``: ``lin`` exposed, GT-mean aligned."""
    img = gt_mean_align(exposed_srgb(lin.cpu()), truth).float()
    rows.setdefault(name, []).append((psnr(img, truth), ssim_metric(img, truth), chroma_noise(img, truth)))


def print_means(rows: Dict[str, List[tuple]], width: int = 12) -> None:
    """One line a candidate: its PSNR / SSIM / chroma_noise, mean over the views."""
    for name, vals in rows.items():
        m = [sum(v[i] for v in vals) / len(vals) for i in range(3)]
        print(f"  {name:{width}s} {m[0]:6.2f} / {m[1]:.3f} / {m[2]:.2f}")


def main(argv: List[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--device", default=None)
    ap.add_argument("--method", default=None, help="the single-view denoiser (default: the run's decomposer.denoise)")
    ap.add_argument("--block", type=int, default=8)
    args = ap.parse_args(argv)
    cfg, scene, model, step = load_run(args.run, args.device)
    device = next(model.parameters()).device
    if args.method:
        cfg.decomposer.denoise = args.method
    spec = denoise_spec(list(scene.train), cfg, str(device))
    if spec is None:
        print("the run's views have no denoiser or no measurable noise: pass --method chroma", file=sys.stderr)
        return 2
    render = render_function(model, cfg, active_sh_degree(cfg, step))
    rows: Dict[str, List[tuple]] = {}
    for view in list(scene.train)[:args.views]:
        truth = view.paired_image
        if truth is None:
            print(f"{view.name}: no normal-light truth, skipped", file=sys.stderr)
            continue
        y = srgb_to_linear_extended(view.load_target().float()).to(device)
        pilot = srgb_to_linear(render(view)["S_rec"].clamp(0, 1)).float()
        today = denoise_linear(y, spec.noise, spec.method, backend=spec.backend).float().to(device)
        wiener = pilot_wiener(y, pilot, spec.noise, args.block)
        cands = {"noisy": y, "today": today, "render": pilot, "wiener": wiener,
                 "wiener-luma": pilot_wiener(y, pilot, spec.noise, args.block, chroma=today)}
        for name, lin in cands.items():
            score(rows, name, lin, truth)
    print(f"run {args.run} (step {step}), {len(next(iter(rows.values()), []))} training views, denoiser "
          f"{spec.method}, {args.block}x{args.block} blocks; GT-mean PSNR / SSIM / chroma_noise, mean over views")
    print_means(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
