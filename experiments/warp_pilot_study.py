"""Do a view's neighbours, warped into it by the model's depth, make a better 2D prior than the render? (issue 64)

The oracle of ``oracle_prior_train.py`` says fox-dark's night gap lies in the priors; the render as the Wiener pilot
(``decomposer.redenoise_at``) gained little because the render lacks the detail too. Burst denoising keeps the
detail: each of the ``--k`` nearest training views (camera centres, facing the same way) is warped into the view
through the trained model's depth (expected depth Σwᵢzᵢ/α), a pixel kept where the source's own depth agrees
within ``--tol`` (occlusion), and the kept light averaged with the view's: unbiased, its noise variance divided by
the count. This study scores, on training views against their normal-light truth (GT-mean, as ``eval``):

- ``noisy``, ``today`` (the single-view denoiser at the scene's strength), ``render``, ``wiener`` (the render as
  pilot: ``decomposer.redenoise_at``'s filter);
- ``warp``: the warped average itself; ``warp+denoise``: today's denoiser on it at the average's noise (the noise
  model ÷ the median count); ``warp+wiener``: the average filtered with the render's Wiener gains at that noise.

Columns: PSNR / SSIM / chroma_noise, mean over views; the median count of views averaged.

    python experiments/warp_pilot_study.py RUN [--views 6] [--k 8] [--tol 0.03] [--device cpu]
"""
from __future__ import annotations

import argparse
import sys
from typing import Dict, List, Tuple

import torch
import torch.nn.functional as F

from retinexgs.data.srgb import srgb_to_linear, srgb_to_linear_extended
from retinexgs.render.rasterize import rasterize_gaussians
from retinexgs.retinex.denoise import DenoiseParams, NoiseModel, denoise_linear, pilot_wiener
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, render_function, view_camera
from retinexgs.train.view_setup import denoise_params, denoise_spec

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from pilot_wiener_study import print_means, score  # noqa: E402


def depth_of(model, view) -> Tuple[torch.Tensor, torch.Tensor]:
    """(expected camera depth [H,W], alpha [H,W]) of the model at ``view``."""
    g = model.gaussians
    cam = model.camera_for(view_camera(view))
    with torch.no_grad():
        ones = torch.ones(len(g), 1, dtype=g.means.dtype, device=g.means.device)
        out = rasterize_gaussians(g.means, g.quats, g.scales, g.opacities, ones, cam, render_depth=True)
    alpha = out.alpha[..., 0].float()
    return out.depth[..., 0].float() / alpha.clamp_min(1e-6), alpha


def warp_average(target, sources, depth, alpha, light, tol: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """(the average of the target's light and its sources' warped in, [H,W,3]; the count averaged [H,W])."""
    H, W = depth.shape
    dev = depth.device
    yy, xx = torch.meshgrid(torch.arange(H, device=dev, dtype=torch.float64) + 0.5,
                            torch.arange(W, device=dev, dtype=torch.float64) + 0.5, indexing="ij")
    z = depth.double()
    cam = torch.stack([(xx - target.cx) / target.fx * z, (yy - target.cy) / target.fy * z, z, torch.ones_like(z)], -1)
    world = cam @ torch.linalg.inv(target.world_to_camera()).to(dev).T  # [H,W,4]
    total = light[target.name].double().clone()
    count = torch.ones(H, W, dtype=torch.float64, device=dev)
    good = alpha > 0.5
    for s in sources:
        p = world @ s.world_to_camera().to(dev).T
        zs = p[..., 2]
        u = s.fx * p[..., 0] / zs.clamp_min(1e-9) + s.cx
        v = s.fy * p[..., 1] / zs.clamp_min(1e-9) + s.cy
        grid = torch.stack([2 * u / s.width - 1, 2 * v / s.height - 1], -1)[None].float()
        img = light[s.name].permute(2, 0, 1)[None].float()
        warped = F.grid_sample(img, grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0].permute(1, 2, 0)
        sd, sa = depth_of.cache[s.name]
        dz = F.grid_sample(sd[None, None], grid, mode="nearest", align_corners=False)[0, 0]
        da = F.grid_sample(sa[None, None], grid, mode="nearest", align_corners=False)[0, 0]
        inside = (u > 0.5) & (u < s.width - 0.5) & (v > 0.5) & (v < s.height - 0.5) & (zs > 0)
        keep = good & inside & (da > 0.5) & ((dz.double() - zs).abs() < tol * zs)
        total += warped.double() * keep[..., None]
        count += keep.double()
    return (total / count[..., None]).float(), count.float()


def neighbours(view, views, k: int) -> List:
    """The ``k`` training views nearest ``view``'s camera centre among those facing within 60° of it."""
    c = view.camera_to_world
    out = []
    for o in views:
        if o is view:
            continue
        cos = float(c[:3, 2] @ o.camera_to_world[:3, 2])
        if cos > 0.5:
            out.append((float((c[:3, 3] - o.camera_to_world[:3, 3]).norm()), o))
    return [o for _, o in sorted(out, key=lambda t: t[0])[:k]]


def main(argv: List[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--k", type=int, default=8)
    ap.add_argument("--tol", type=float, default=0.03)
    ap.add_argument("--device", default=None)
    ap.add_argument("--clean", default=None, help="the noise-free capture of the same scene: warp its light instead "
                    "(the warp's own error, no noise)")
    ap.add_argument("--full", action="store_true", help="the denoiser on the average at its full strength (not "
                    "lightened for the views per point)")
    args = ap.parse_args(argv)
    cfg, scene, model, step = load_run(args.run, args.device)
    device = next(model.parameters()).device
    train = list(scene.train)
    spec = denoise_spec(train, cfg, str(device))
    if spec is None:
        print("the run's views have no denoiser or no measurable noise", file=sys.stderr)
        return 2
    params = denoise_params(cfg, scene.views_per_point())
    render = render_function(model, cfg, active_sh_degree(cfg, step))
    light = {v.name: srgb_to_linear_extended(v.load_target().float()).to(device) for v in train}
    if args.clean:
        from retinexgs.run.folder import open_scene
        clean = {v.name: v for v in open_scene(args.clean, cfg).train}
        light = {n: srgb_to_linear_extended(clean[n].load_target().float()).to(device) for n in light}
    full = DenoiseParams.from_mapping(cfg.decomposer.denoise_params) if args.full else params
    depth_of.cache = {v.name: depth_of(model, v) for v in train}
    rows: Dict[str, List[tuple]] = {}
    counts = []
    picks = train[::max(1, len(train) // args.views)][:args.views]
    for view in picks:
        truth = view.paired_image
        if truth is None:
            continue
        y = light[view.name]
        pilot = srgb_to_linear(render(view)["S_rec"].clamp(0, 1)).float()
        today = denoise_linear(y, spec.noise, spec.method, params, backend=spec.backend).float().to(device)
        avg, count = warp_average(view, neighbours(view, train, args.k), *depth_of.cache[view.name], light, args.tol)
        n = float(count.median())
        counts.append(n)
        noise_n = NoiseModel(tuple(a / n for a in spec.noise.a), tuple(b / n for b in spec.noise.b))
        cands = {"noisy": y, "today": today, "render": pilot, "wiener": pilot_wiener(y, pilot, spec.noise),
                 "warp": avg,
                 "warp+denoise": denoise_linear(avg, noise_n, spec.method, full, backend=spec.backend).float(),
                 "warp+wiener": pilot_wiener(avg, pilot, noise_n)}
        for name, lin in cands.items():
            score(rows, name, lin, truth)
    print(f"run {args.run} (step {step}), {len(counts)} training views, k {args.k}, tol {args.tol}, median count "
          f"{sorted(counts)[len(counts) // 2]:.1f}; GT-mean PSNR / SSIM / chroma_noise, mean over views")
    print_means(rows, 13)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
