"""Where a run's test views get their light from near the camera, and what a near plane would change
(experiments/notes/2026-11-28-near-plane.md): for each trained run,

1. per test view, the share of its compositing weight (Σ over pixels of each Gaussian's αT) that comes from
   Gaussians closer to the camera than f × the training views' nearest content depth
   (:func:`retinexgs.model.near_plane.content_depth`), f in ``--shares``;
2. the test views' metrics re-evaluated with the near plane at F × that depth, F in ``--fractions`` (0: the
   renderer's own 0.01; the run's own plane is replaced), written under ``--out``.

    python experiments/near_plane_study.py RUN... --out DIR [--fractions 0 0.1 0.2] [--device cpu]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

import retinexgs.run.render as run_render
from retinexgs.evaluate.evaluate import evaluate
from retinexgs.model.near_plane import content_depth, with_near
from retinexgs.render import rasterize_gaussians
from retinexgs.run.folder import load_run


def weight_by_depth(model, camera):
    """([N] Σ over the frame's pixels of each Gaussian's compositing weight, [N] its camera-space depth)."""
    g = model.gaussians
    probe = torch.ones(len(g), 1, device=g.means.device, requires_grad=True)
    out = rasterize_gaussians(g.means.detach(), g.quats.detach(), g.scales.detach(), g.opacities.detach(), probe,
                              camera, validate=False)
    out.image.sum().backward()
    vm = camera.viewmat.to(g.means)
    z = g.means.detach() @ vm[:3, :3].T + vm[:3, 3]
    return probe.grad[:, 0], z[:, 2]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--shares", type=float, nargs="+", default=[0.05, 0.1, 0.2])
    p.add_argument("--fractions", type=float, nargs="+", default=[0.0, 0.1, 0.2])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = p.parse_args(argv)
    view_camera = run_render.view_camera
    for run in args.runs:
        cfg, scene, model, step = load_run(run, args.device)
        depth = content_depth(scene.points, [view_camera(v) for v in scene.train])
        print(f"{run}: the training views' nearest content depth {depth:.4g}")
        for v in scene.test:
            w, z = weight_by_depth(model, view_camera(v))
            total = float(w.sum())
            shares = ", ".join(f"< {f:g}: {float(w[z < f * depth].sum()) / total:.3f}" for f in args.shares)
            print(f"  {v.name}: weight share at depth (x nearest content) {shares}")
        if model.has_near:
            model.near.zero_()  # the study's plane replaces the run's own
        for frac in args.fractions:
            near = frac * depth
            run_render.view_camera = (lambda v, near=near: with_near(view_camera(v), near)) if near > 0 else view_camera
            out = args.out / run.name / f"near_{frac:g}"
            out.mkdir(parents=True, exist_ok=True)
            m = evaluate(run_render.render_function(model, cfg, run_render.active_sh_degree(cfg, step)), scene, out,
                         False, log=lambda s: None)
            run_render.view_camera = view_camera
            mm = m["mean"]
            print(f"  near {frac:g} x ({near:.4g}): GT-mean {mm['psnr_gt_mean']:.2f} / {mm['ssim_gt_mean']:.3f}, "
                  f"ΔE {mm['delta_e_gt_mean']:.2f}, lift {mm['black_lift']:+.4f}; ΔE per view "
                  + " ".join(f"{r['delta_e_gt_mean']:.1f}" for r in m["views"]))
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
