"""Would a BM3D-class luma denoiser make better priors than today's NLM on a night view? (issue 64 item 1)

What limits fox-dark's SSIM at 1000 e⁻ is detail the fit does not recover, not noise left in the render
(experiments/notes/2026-11-29-luma-views.md §8), and a detail-preserving denoiser is the candidate left. Before
building one, this measures the premise on single views: each of the first ``--views`` training views of a capture
(its linear light as training reads it) through

- ``today``: ``decomposer.denoise``'s ``chroma`` (GAT, NLM luma at ``h_luma`` σ, the luma-guided chroma, unbiased
  inverse), ``--h-luma`` as given (0.8: a lone view; 0.41: fox-dark's strength by its views per point);
- ``bm3d``: the same transform and chroma filter, the luma by BM3D (both stages) at the measured σ × ``--bm3d-scale``;
- ``bm3d-psd``: BM3D given the luma noise's power spectrum instead of one σ: the raw views' noise is coarse (the
  demosaic and the colour matrix correlate it, experiments/notes/2026-11-28-denoise-prior.md §2), estimated from the
  periodogram of today's luma residual, smoothed.

and scores each against the view's normal-light truth (exposed by one gain to a mean luma of 0.18, sRGB, GT-mean
aligned as `eval` does): PSNR / SSIM. BM3D here is the Tampere reference package (`pip install bm3d`, licensed for
non-commercial use only): a measurement of what the class of method gives, never a dependency of the package.

    python experiments/bm3d_luma_study.py CAPTURE [--views 4] [--h-luma 0.8] [--bm3d-scale 1.0]
"""
from __future__ import annotations

import argparse
import sys
from typing import Dict, List

import numpy as np
import torch

from bm3d_prior_train import load_bm3d
from pilot_wiener_study import exposed_srgb
from retinexgs.data.srgb import srgb_to_linear_extended
from retinexgs.evaluate.metrics import gt_mean_align, psnr, ssim_metric
from retinexgs.retinex import denoise as dn
from retinexgs.run.config import load_config
from retinexgs.run.folder import open_scene
from retinexgs.train.view_setup import denoise_spec


def smoothed_psd(residual: np.ndarray, radius: int = 4) -> np.ndarray:
    """The periodogram |FFT|² of ``residual`` [H,W] (BM3D's normalisation: σ²·H·W for white noise σ), box-smoothed
    over (2·radius+1)² frequencies with wrap-around."""
    p = np.abs(np.fft.fft2(residual)) ** 2
    k = 2 * radius + 1
    out = np.zeros_like(p)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            out += np.roll(np.roll(p, dy, 0), dx, 1)
    return out / (k * k)


def stabilised(lin: torch.Tensor, noise: dn.NoiseModel, h_luma: float):
    """Today's transform of one view ``lin`` [H,W,3]: (its GAT [H,W,3], the luma/chroma split [3,H,W], each
    channel's measured σ, ``finish(luma)``: the linear light of a luma with today's luma-guided chroma, today's luma
    NLM at ``h_luma`` σ)."""
    p = dn.DenoiseParams(h_luma=h_luma)
    d = dn.gat_forward(lin.double(), noise.a, noise.b)
    ycc = torch.einsum("ij,hwj->ihw", dn.YCC.to(d), d)
    sig = [max(1.0, dn._measured_sigma(c)) for c in ycc]
    h, w = ycc.shape[-2:]
    r = int(max(1, min(round(p.radius * w / 640.0), (min(h, w) - 1) // 2)))

    def finish(luma: torch.Tensor) -> torch.Tensor:
        chroma = torch.cat([dn._guided(luma[None], c[None], r, p.eps * s * s) for c, s in zip(ycc[1:], sig[1:])])
        out = torch.einsum("ij,ihw->hwj", dn.YCC.to(d), torch.cat([luma[None], chroma]))
        return dn.gat_inverse(out, noise.a, noise.b).float()

    return d, ycc, sig, finish, dn._nlm_any(ycc[0], p.h_luma * sig[0], p, "opencv")


def run(lin: torch.Tensor, noise: dn.NoiseModel, h_luma: float, bm3d_scale: float) -> Dict[str, torch.Tensor]:
    """The candidates' linear light for one view ``lin`` [H,W,3]."""
    bm3d = load_bm3d()
    _, ycc, sig, finish, luma_today = stabilised(lin, noise, h_luma)
    y0 = ycc[0].numpy()
    luma_bm3d = torch.from_numpy(np.asarray(bm3d.bm3d(y0, sig[0] * bm3d_scale)).reshape(y0.shape)).to(ycc)
    psd = smoothed_psd(y0 - luma_today.numpy()) * bm3d_scale ** 2
    luma_psd = torch.from_numpy(np.asarray(bm3d.bm3d(y0, psd)).reshape(y0.shape)).to(ycc)
    return {"noisy": lin.float(), "today": finish(luma_today), "bm3d": finish(luma_bm3d),
            "bm3d-psd": finish(luma_psd)}


def capture_views(capture: str):
    """(the capture's training views, their denoiser spec with ``decomposer.denoise: chroma``), or None with one
    line on stderr where its noise cannot be measured."""
    cfg = load_config([], ["decomposer.denoise=chroma"])
    views = list(open_scene(capture, cfg).train)
    spec = denoise_spec(views, cfg, "cpu")
    if spec is None:
        print("the capture's noise could not be measured", file=sys.stderr)
        return None
    return views, spec


def sampled_views(capture: str, n: int):
    """(n training views of ``capture``, evenly spaced, each with its linear light as training reads it; the views'
    noise model), or None with one line on stderr where the noise cannot be measured."""
    opened = capture_views(capture)
    if opened is None:
        return None
    views, spec = opened
    step = max(1, len(views) // n)
    return [(v, srgb_to_linear_extended(v.load_target().float())) for v in views[::step][:n]], spec.noise


def study_parser(doc: str) -> argparse.ArgumentParser:
    """The single-view studies' arguments: the capture, how many views, today's luma strength."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--h-luma", type=float, default=0.8)
    return ap


def main(argv: List[str]) -> int:
    ap = study_parser(__doc__)
    ap.add_argument("--bm3d-scale", type=float, default=1.0)
    args = ap.parse_args(argv)
    sampled = sampled_views(args.capture, args.views)
    if sampled is None:
        return 2
    rows: Dict[str, List[tuple]] = {}
    for view, y in sampled[0]:
        truth = view.paired_image
        for name, lin in run(y, sampled[1], args.h_luma, args.bm3d_scale).items():
            img = gt_mean_align(exposed_srgb(lin), truth).float()
            rows.setdefault(name, []).append((psnr(img, truth), ssim_metric(img, truth)))
        print(view.name, {k: f"{v[-1][0]:.2f}/{v[-1][1]:.3f}" for k, v in rows.items()}, flush=True)
    print(f"{args.capture}: {len(rows['noisy'])} views, h_luma {args.h_luma}, bm3d σ × {args.bm3d_scale}; "
          "GT-mean PSNR / SSIM, mean over the views")
    for name, vals in rows.items():
        print(f"  {name:9s} {np.mean([v[0] for v in vals]):6.2f} / {np.mean([v[1] for v in vals]):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
