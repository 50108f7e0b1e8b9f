"""Where a trained run's error against the normal-light truth comes from, from its evaluation panels.

    python scripts/gap_analysis.py RUN [RUN ...] [--ceiling RUN ...]

Each RUN is a trained run with ``renders/test/*.png`` (the panels ``retinexgs eval`` writes: low input | output |
... | ground truth). For every run, averaged over its test views:

- PSNR / SSIM as evaluated;
- the same after an oracle *tone* correction that uses the truth: a per-channel affine fit, and a per-channel
  histogram match (any monotone curve). What these recover is tone and colour; what they leave is structure;
- SSIM after a Gaussian blur of σ = 0.8 px (a gain means uncorrelated high-frequency error, e.g. noise);
- SSIM's three terms (luminance, contrast, structure) and the ratio of local standard deviations (output / truth);
- the per-channel affine slope: < 1 means the output has more contrast than the truth, > 1 less;
- the exposure level: the output re-exposed in linear light, srgb(c·lin(output)) (what a change of the exposure
  gain does, up to clipping of the 8-bit PNG), with the best c per view (an oracle that uses the truth: the most any
  exposure rule could give) and with the c at which an averaging meter (the image's mean) or a centre-weighted
  meter (a Gaussian weight of σ = 0.35 of the frame, as a camera's centre-weighted mode) reads 0.5 (rules that
  do not look at the truth); and the mean of the output and of the truth;
- the tone's ends: the 1st, 50th and 99th percentiles of the output's and the truth's values (where a camera's
  tone curve shows: its toe, its mid-grey, its shoulder).

``--ceiling`` runs (e.g. plain 3DGS trained on the normal-light photos themselves) are scored the same way: the
3D reconstruction's own ceiling on those views. No GPU needed; the numbers of
experiments/notes/2026-11-24-remaining-gap.md came from this script on runs copied back from the GPU machine.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from retinexgs.evaluate.metrics import psnr, ssim_metric
from retinexgs.model.tone import linear_to_srgb, srgb_to_linear


def panels(path: Path, count: int, top: int = 0) -> List[torch.Tensor]:
    """The ``count`` [H,W,3] panels of one evaluation PNG (equal widths side by side) below its ``top`` rows (the
    strip naming the panels: metrics.json's ``label_rows``)."""
    a = np.asarray(Image.open(path).convert("RGB")).astype(np.float32)[top:] / 255.0
    if a.shape[1] % count:
        raise SystemExit(f"{path}: width {a.shape[1]} is not {count} equal panels")
    w = a.shape[1] // count
    return [torch.from_numpy(a[:, i * w:(i + 1) * w].copy()) for i in range(count)]


def label_rows(run: Path) -> int:
    """Rows of the panel-name strip above the run's evaluation PNGs (0 for runs evaluated before it existed)."""
    import json

    try:
        return int(json.loads((run / "metrics.json").read_text()).get("label_rows", 0))
    except (OSError, ValueError):
        return 0


def panel_count(run: Path) -> int:
    """How many panels the run's evaluation PNGs hold (metrics.json names them, e.g. "low input | output | ...")."""
    import json

    try:
        return len(json.loads((run / "metrics.json").read_text())["panels"].split("|"))
    except (OSError, KeyError, ValueError) as err:
        raise SystemExit(f"{run}: cannot read the panel layout from metrics.json ({err})")


def _gauss(sigma: float, radius: int) -> torch.Tensor:
    t = torch.arange(-radius, radius + 1, dtype=torch.float64)
    g = torch.exp(-t ** 2 / (2 * sigma ** 2))
    return g / g.sum()


def blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of an [H,W,C] image (reflect padding)."""
    r = max(1, int(3 * sigma + 0.5))
    g = _gauss(sigma, r).to(x.dtype)
    c = x.shape[-1]
    t = x.permute(2, 0, 1)[None]
    t = F.conv2d(F.pad(t, (r, r, 0, 0), mode="reflect"), g.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    t = F.conv2d(F.pad(t, (0, 0, r, r), mode="reflect"), g.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)
    return t[0].permute(1, 2, 0)


def affine_fit(x: torch.Tensor, y: torch.Tensor):
    """Per-channel least-squares a·x + b ≈ y: (corrected image, slopes [C])."""
    out, slopes = torch.empty_like(x), []
    for ch in range(x.shape[-1]):
        xs = x[..., ch].reshape(-1).double()
        A = torch.stack([xs, torch.ones_like(xs)], 1)
        a, b = torch.linalg.lstsq(A, y[..., ch].reshape(-1, 1).double()).solution.reshape(-1).tolist()
        out[..., ch] = (a * x[..., ch] + b).float()
        slopes.append(a)
    return out.clamp(0, 1), slopes


def histogram_match(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-channel histogram matching of x to y (the best monotone curve, rank for rank)."""
    out = torch.empty_like(x)
    for ch in range(x.shape[-1]):
        _, order = x[..., ch].reshape(-1).sort()
        target, _ = y[..., ch].reshape(-1).sort()
        flat = torch.empty_like(target)
        flat[order] = target
        out[..., ch] = flat.reshape(x.shape[:2])
    return out


def ssim_terms(x: torch.Tensor, y: torch.Tensor) -> Dict[str, float]:
    """Means of SSIM's luminance, contrast and structure terms (11×11 window, σ 1.5, valid), and the ratio of the
    mean local standard deviations x / y."""
    g = _gauss(1.5, 5)
    k = (g[:, None] * g[None, :])[None, None].repeat(3, 1, 1, 1)
    a, b = x.permute(2, 0, 1)[None].double(), y.permute(2, 0, 1)[None].double()

    def f(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, k, groups=3)

    mx, my = f(a), f(b)
    vx, vy, cxy = f(a * a) - mx ** 2, f(b * b) - my ** 2, f(a * b) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    sx, sy = vx.clamp_min(0).sqrt(), vy.clamp_min(0).sqrt()
    return {"l": float(((2 * mx * my + c1) / (mx ** 2 + my ** 2 + c1)).mean()),
            "c": float(((2 * sx * sy + c2) / (vx + vy + c2)).mean()),
            "s": float(((cxy + c2 / 2) / (sx * sy + c2 / 2)).mean()),
            "std_ratio": float(sx.mean() / sy.mean())}


def centre_weights(h: int, w: int, sigma: float = 0.35) -> torch.Tensor:
    """[H,W] Gaussian weights about the frame's centre, σ a fraction of its height and width, summing to 1."""
    y = (torch.arange(h, dtype=torch.float64) + 0.5 - h / 2) / (sigma * h)
    x = (torch.arange(w, dtype=torch.float64) + 0.5 - w / 2) / (sigma * w)
    wts = torch.exp(-(y[:, None] ** 2 + x[None, :] ** 2) / 2)
    return wts / wts.sum()


def exposure_for(meter, lin: torch.Tensor, target: float) -> float:
    """The gain c with meter(srgb(c·lin)) = target (bisection over 0.2-5: every meter grows with c)."""
    lo, hi = 0.2, 5.0
    for _ in range(40):
        c = (lo + hi) / 2
        lo, hi = (c, hi) if meter(linear_to_srgb(c * lin)) < target else (lo, c)
    return (lo + hi) / 2


def level_terms(out: torch.Tensor, gt: torch.Tensor) -> Dict[str, float]:
    """PSNR with the output re-exposed in linear light: the best gain c (a grid over 0.5-2), the averaging and
    the centre-weighted meter at 0.5; that c, and the mean of output and truth."""
    lin = srgb_to_linear(out.double())
    gt = gt.double()
    cw = centre_weights(*out.shape[:2])
    meters = {"mean": lambda x: float(x.mean()), "centre": lambda x: float((x.mean(-1) * cw).sum())}
    best_psnr, best_c = max((psnr(linear_to_srgb(c * lin), gt), c) for c in np.linspace(0.5, 2.0, 151).tolist())
    row = {"psnr_gain": best_psnr, "gain": best_c, "mean_out": float(out.mean()), "mean_truth": float(gt.mean())}
    for q in (1, 50, 99):
        row[f"p{q}_out"] = float(torch.quantile(out.double().reshape(-1), q / 100))
        row[f"p{q}_truth"] = float(torch.quantile(gt.reshape(-1), q / 100))
    for name, meter in meters.items():
        row[f"psnr_{name}_meter"] = psnr(linear_to_srgb(exposure_for(meter, lin, 0.5) * lin), gt)
    return row


def analyse(run: Path) -> Dict[str, float]:
    """The averages described in the module docstring, over the run's test panels."""
    files = sorted((run / "renders" / "test").glob("*.png"))
    if not files:
        raise SystemExit(f"{run}: no renders/test/*.png (evaluate the run first: retinexgs eval --run {run})")
    rows, count, top = [], panel_count(run), label_rows(run)
    for path in files:
        p = panels(path, count, top)
        out, gt = p[1], p[-1]
        aff, slopes = affine_fit(out, gt)
        hm = histogram_match(out, gt)
        terms = ssim_terms(out, gt)
        rows.append({"psnr": psnr(out, gt), "ssim": ssim_metric(out, gt),
                     "psnr_affine": psnr(aff, gt), "ssim_affine": ssim_metric(aff, gt),
                     "psnr_hist": psnr(hm, gt), "ssim_hist": ssim_metric(hm, gt),
                     "ssim_blur": ssim_metric(blur(out, 0.8), gt),
                     **{f"term_{k}": v for k, v in terms.items()}, **level_terms(out, gt),
                     **{f"slope_{c}": s for c, s in zip("rgb", slopes)}})
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]} | {"views": len(rows)}


def main(argv: List[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--ceiling", nargs="*", type=Path, default=[], help="runs scored as reconstruction ceilings")
    args = ap.parse_args(argv)
    print("| run | PSNR / SSIM | tone oracle: affine | tone oracle: histogram | SSIM, blur 0.8 px | "
          "SSIM terms l / c / s | local std out/truth | affine slope r / g / b | exposure oracle: best gain (c) | "
          "meter at 0.5: mean / centre-weighted | mean out / truth | p1, p50, p99 out / truth |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for run in [*args.runs, *args.ceiling]:
        m = analyse(run)
        tag = " (ceiling)" if run in args.ceiling else ""
        print(f"| {run}{tag} | {m['psnr']:.2f} / {m['ssim']:.3f} | {m['psnr_affine']:.2f} / {m['ssim_affine']:.3f} | "
              f"{m['psnr_hist']:.2f} / {m['ssim_hist']:.3f} | {m['ssim_blur']:.3f} | "
              f"{m['term_l']:.3f} / {m['term_c']:.3f} / {m['term_s']:.3f} | {m['term_std_ratio']:.2f} | "
              f"{m['slope_r']:.2f} / {m['slope_g']:.2f} / {m['slope_b']:.2f} | {m['psnr_gain']:.2f} ({m['gain']:.2f}) | "
              f"{m['psnr_mean_meter']:.2f} / {m['psnr_centre_meter']:.2f} | {m['mean_out']:.3f} / {m['mean_truth']:.3f} | "
              f"{m['p1_out']:.3f}, {m['p50_out']:.3f}, {m['p99_out']:.3f} / "
              f"{m['p1_truth']:.3f}, {m['p50_truth']:.3f}, {m['p99_truth']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
