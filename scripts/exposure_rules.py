"""How far each exposure rule lands from the best exposure, on trained runs (a development tool, CPU or GPU).

    python scripts/exposure_rules.py RUN... [--device cpu]

For every test view of each run (R̂ and L̂ rendered once), the gamma g of a tone form is solved so that a statistic
of the enhanced image equals a target (bisection: each statistic falls as g grows), and the result is scored
against the normal-light photo. No EnhancementNet is involved: this is the rule itself, exactly met, which is what
L_exp asks the net for. Rows:
- ``oracle``: the g with the best PSNR per view (a grid over 0.2-2.0), i.e. the best any rule could do;
- ``truth``: the statistic measured on the normal-light photos (what a rule would have to guess);
- one row per (statistic, target): ``img_mean`` (the sRGB image's mean: a camera's averaging meter, the default at
  0.5), ``lin_mean`` (mean linear luminance), ``log_avg`` (log-average linear luminance, the photographic "key"),
  ``median`` (of sRGB luminance), ``light_mean`` (the enhanced light L_enh's mean: ``exp_on: illumination``).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable, Dict, List, Tuple

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from retinexgs.evaluate.metrics import psnr, ssim_metric  # noqa: E402
from retinexgs.model.tone import srgb_to_linear, tone_map  # noqa: E402

LUMA = torch.tensor([0.2126, 0.7152, 0.0722])
STATS: Dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {
    "img_mean": lambda S, Le: S.mean(),
    "lin_mean": lambda S, Le: (srgb_to_linear(S) @ LUMA.to(S)).mean(),
    "log_avg": lambda S, Le: torch.exp(torch.log(srgb_to_linear(S) @ LUMA.to(S) + 1e-3).mean()),
    "median": lambda S, Le: (S @ LUMA.to(S)).median(),
    "light_mean": lambda S, Le: Le.mean(),
}
TARGETS = {"img_mean": (0.45, 0.5, 0.55), "lin_mean": (0.18, 0.21, 0.25), "log_avg": (0.13, 0.18, 0.22),
           "median": (0.46, 0.5, 0.55), "light_mean": (0.5, 0.55, 0.6)}


def solve(R: torch.Tensor, L: torch.Tensor, ref: torch.Tensor, tone: str, stat: str, target: float) -> float:
    """The g in [0.05, 3] at which ``stat`` of the enhanced image equals ``target`` (bisection; the bound nearest
    to it where no g in that range reaches it)."""
    lo, hi = 0.05, 3.0
    for _ in range(30):
        g = 0.5 * (lo + hi)
        S, Le = tone_map(R, L, ref, torch.tensor(g, dtype=R.dtype), tone)
        lo, hi = (g, hi) if STATS[stat](S, Le) > target else (lo, g)
    return 0.5 * (lo + hi)


def score(views: List[Tuple[torch.Tensor, torch.Tensor, torch.Tensor]], ref: torch.Tensor, tone: str,
          pick: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], float]) -> Tuple[float, float]:
    """Mean PSNR / SSIM over ``views`` [(R̂, L̂, truth)] with g = pick(R̂, L̂, truth) per view."""
    out = []
    for R, L, gt in views:
        S, _ = tone_map(R, L, ref, torch.tensor(pick(R, L, gt), dtype=R.dtype), tone)
        out.append((psnr(S, gt), ssim_metric(S, gt)))
    t = torch.tensor(out, dtype=torch.float64).mean(0)
    return float(t[0]), float(t[1])


def main(argv: List[str]) -> int:
    from retinexgs.run.folder import load_run
    from retinexgs.run.render import active_sh_degree, view_camera

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--tones", nargs="+", default=["exposure", "illumination"])
    args = ap.parse_args(argv)
    grid = torch.linspace(0.2, 2.0, 91).tolist()
    print("| run | tone | rule | PSNR / SSIM |\n|---|---|---|---|")
    for run in args.runs:
        cfg, scene, model, step = load_run(run, args.device)
        model.eval()
        degree, ref = active_sh_degree(cfg, step), model.illum_ref
        views = []
        with torch.no_grad():
            for v in scene.test:
                if v.paired_path is not None:
                    res = model.render(view_camera(v), degree, enhance=False)
                    views.append((res["R"], res["L"], v.paired_image.to(res["R"])))
        if not views:
            print(f"{run}: no test view with a normal-light photo", file=sys.stderr)
            return 2
        truth = {k: sum(float(STATS[k](gt, gt)) for _, _, gt in views) / len(views) for k in STATS if k != "light_mean"}
        print(f"| {run.name} | – | truth: " + ", ".join(f"{k} {v:.3f}" for k, v in truth.items()) + " | – |")
        for tone in args.tones:
            with torch.no_grad():
                best = score(views, ref, tone, lambda R, L, gt: max(
                    grid, key=lambda g: psnr(tone_map(R, L, ref, torch.tensor(g, dtype=R.dtype), tone)[0], gt)))
                print(f"| {run.name} | {tone} | oracle (best g per view) | {best[0]:.2f} / {best[1]:.3f} |", flush=True)
                for stat, targets in TARGETS.items():
                    for target in targets:
                        p, s = score(views, ref, tone, lambda R, L, gt: solve(R, L, ref, tone, stat, target))
                        print(f"| {run.name} | {tone} | {stat} = {target} | {p:.2f} / {s:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
