"""Score trained runs' test views with a render-time white balance (issue 53): PSNR, SSIM, the GT-mean figures and
the colour error (ΔE of the average colours after GT-mean) as `eval` computes them, as trained and with each form.

    python experiments/white_balance_eval.py RUN... [--forms as-trained,auto] [--device cuda]

Prints one row per run and form, and writes RUN/white_balance/<form>/metrics.json (renders beside it).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from retinexgs.evaluate.evaluate import evaluate
from retinexgs.model.white_balance import describe_balance, parse_white_balance
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, render_function, white_balance_of


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--forms", default="as-trained,auto")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = p.parse_args(argv)
    keys = ("psnr", "ssim", "psnr_gt_mean", "ssim_gt_mean", "delta_e_gt_mean")
    print("run | form | " + " | ".join(keys))
    for run in args.runs:
        cfg, scene, model, step = load_run(run, args.device)
        degree = active_sh_degree(cfg, step)
        for form in args.forms.split(","):
            wb = parse_white_balance(form)
            balance = white_balance_of(wb, model, cfg, scene, degree)
            out = run / "white_balance" / form.replace(":", "_")
            metrics = evaluate(render_function(model, cfg, degree, balance=balance), scene, out, False,
                               log=lambda s: None)
            m = metrics["mean"]
            print(f"{run.name} | {describe_balance(wb, balance)} | " + " | ".join(f"{m[k]:.4f}" for k in keys))
            sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
