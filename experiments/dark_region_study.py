"""Where does a night capture's SSIM go: the dark, middle or bright third of the scene, and is the model there better
or worse than the denoised view it was supervised by? (issue 64)

For a trained run, each view's evaluation SSIM map (11×11 Gaussian window, valid, as `eval`) of a candidate image
against the view's normal-light truth, GT-mean aligned, is averaged over three regions: the truth's grey (Rec. 601)
below its 1/3 quantile, between, and above its 2/3 quantile (a night capture's electrons follow the scene's
brightness, so these are its low-, mid- and high-SNR thirds). Candidates:

- test views: ``enhanced`` (what `eval` scores) and ``render`` (the model's R̂∘L̂, exposed by one gain as below);
- training views (the first ``--views``): ``noisy`` (the view's light as training reads it), ``today`` (the run's
  single-view denoiser, what LR3M decomposes for the priors) and ``render``.

And, per test view and third, the Gaussians whose centres project there (in front of the camera, opacity ≥ 0.05) per
1000 pixels of that third, and their median projected radius in pixels (3σ of the largest scale, at the centre's
depth): a third the densification left coarse has few, large Gaussians.

Linear candidates are exposed by one gain (mean luma to 0.18) and sRGB-encoded before the alignment, as in
``pilot_wiener_study.py``. Columns: SSIM over the whole view (as `eval`), then the three thirds; mean over the views.

    python experiments/dark_region_study.py RUN [--views 8] [--device cpu]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List

import torch

from retinexgs.data.srgb import srgb_to_linear, srgb_to_linear_extended
from retinexgs.evaluate.metrics import gt_mean_align, ssim
from retinexgs.retinex.denoise import denoise_linear
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, render_function
from retinexgs.train.view_setup import denoise_spec

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pilot_wiener_study import exposed_srgb  # noqa: E402

_GREY = (0.299, 0.587, 0.114)
_PAD = 5  # the valid SSIM map is the image less 5 pixels at each side


def region_ssim(img: torch.Tensor, truth: torch.Tensor) -> List[float]:
    """[whole, dark, mid, bright] mean evaluation SSIM of ``img`` against ``truth`` ([H,W,3] sRGB in [0,1]),
    ``img`` GT-mean aligned first; the thirds by the truth's grey quantiles."""
    a = gt_mean_align(img.cpu().float(), truth.cpu().float()).float()
    b = truth.cpu().float()
    m = ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], padding="valid", reduction="none")[0].mean(0)
    grey = (b * b.new_tensor(_GREY)).sum(-1)[_PAD:-_PAD, _PAD:-_PAD]
    lo, hi = torch.quantile(grey.flatten(), grey.new_tensor([1 / 3, 2 / 3]))
    masks = [torch.ones_like(grey, dtype=torch.bool), grey < lo, (grey >= lo) & (grey <= hi), grey > hi]
    return [float(m[k].mean()) for k in masks]


def region_density(model, view, truth: torch.Tensor) -> List[float]:
    """[per 1000 px dark, mid, bright; median radius px dark, mid, bright] of the model's Gaussians at ``view``."""
    g = model.gaussians
    with torch.no_grad():
        means = g.means.detach().double().cpu()
        w2c = view.world_to_camera().double().cpu()
        p = means @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        u = view.fx * p[:, 0] / z.clamp_min(1e-9) + view.cx
        v = view.fy * p[:, 1] / z.clamp_min(1e-9) + view.cy
        radius = 3 * g.scales.detach().double().cpu().amax(-1) * view.fx / z.clamp_min(1e-9)
        opacity = g.opacities.detach().double().cpu().reshape(-1)
    b = truth.cpu().float()
    grey = (b * b.new_tensor(_GREY)).sum(-1)
    lo, hi = torch.quantile(grey.flatten(), grey.new_tensor([1 / 3, 2 / 3]))
    inside = (z > 0) & (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height) & (opacity >= 0.05)
    gy = grey[v[inside].long().clamp(0, grey.shape[0] - 1), u[inside].long().clamp(0, grey.shape[1] - 1)]
    r = radius[inside].float()
    third = [gy < lo, (gy >= lo) & (gy <= hi), gy > hi]
    area = [float((grey < lo).sum()), float(((grey >= lo) & (grey <= hi)).sum()), float((grey > hi).sum())]
    return ([1000 * float(t.sum()) / a for t, a in zip(third, area)]
            + [float(r[t].median()) if bool(t.any()) else float("nan") for t in third])


def add(rows: Dict[str, List[List[float]]], name: str, img: torch.Tensor, truth: torch.Tensor) -> None:
    rows.setdefault(name, []).append(region_ssim(img, truth))


def show(title: str, rows: Dict[str, List[List[float]]]) -> None:
    if not rows:
        print(f"{title}: no view with a normal-light truth")
        return
    n = len(next(iter(rows.values())))
    print(f"{title}: SSIM whole / dark / mid / bright third (the truth's grey), mean over {n} views")
    for name, vals in rows.items():
        m = [sum(v[i] for v in vals) / len(vals) for i in range(4)]
        print(f"  {name:10s} {m[0]:.3f} / {m[1]:.3f} / {m[2]:.3f} / {m[3]:.3f}")


def main(argv: List[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--device", default=None)
    args = ap.parse_args(argv)
    cfg, scene, model, step = load_run(args.run, args.device)
    device = next(model.parameters()).device
    render = render_function(model, cfg, active_sh_degree(cfg, step))
    test: Dict[str, List[List[float]]] = {}
    density: List[List[float]] = []
    for view in scene.test:
        truth = view.paired_image
        if truth is None:
            continue
        out = render(view)
        add(test, "enhanced", out["rgb"].clamp(0, 1), truth)
        add(test, "render", exposed_srgb(srgb_to_linear(out["S_rec"].clamp(0, 1)).float().cpu()), truth)
        density.append(region_density(model, view, truth))
    show(f"run {args.run} (step {step}), test views", test)
    d = [sum(x[i] for x in density) / max(len(density), 1) for i in range(6)]
    print(f"  Gaussians per 1000 px, dark / mid / bright: {d[0]:.1f} / {d[1]:.1f} / {d[2]:.1f}; median radius px "
          f"{d[3]:.1f} / {d[4]:.1f} / {d[5]:.1f}")
    spec = denoise_spec(list(scene.train), cfg, str(device))
    train: Dict[str, List[List[float]]] = {}
    for view in list(scene.train)[:args.views]:
        truth = view.paired_image
        if truth is None:
            continue
        y = srgb_to_linear_extended(view.load_target().float()).to(device)
        add(train, "noisy", exposed_srgb(y.cpu()), truth)
        if spec is not None:
            today = denoise_linear(y, spec.noise, spec.method, backend=spec.backend).float()
            add(train, "today", exposed_srgb(today.cpu()), truth)
        add(train, "render", exposed_srgb(srgb_to_linear(render(view)["S_rec"].clamp(0, 1)).float().cpu()), truth)
    show("training views", train)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
