"""Would Intel Open Image Denoise (a pretrained, Apache-2.0 network) make better priors than today's NLM on a night
view? (issue 64 item 1)

Every classical denoiser tried on fox-dark at 1000 e⁻ lost the detail the fit needs (NLM, BM3D, FFDNet:
experiments/notes/2026-11-30-bm3d-luma.md); priors from the noise-free capture lift the trained SSIM from 0.74 to
0.88 (r-prior-chroma §4-5). OIDN is a U-Net trained on rendering noise and shipped with its weights (`pip install
pyoidn`: MIT binding, OIDN Apache-2.0, CPU and CUDA devices). Its premise, measured on single views as
bm3d_luma_study.py does: each of the first ``--views`` training views of a capture through

- ``today``: ``decomposer.denoise``'s ``chroma`` at ``--h-luma``;
- ``oidn``: OIDN (HDR, quality high) on the view's linear light;
- ``oidn-gat``: OIDN (LDR) on the variance-stabilised view (GAT at the measured noise), scaled into [0, 1], inverted;
- ``oidn+chroma``: OIDN's luma, today's luma-guided chroma filter (in the GAT domain);

scored against the view's normal-light truth (exposed to a mean luma of 0.18, sRGB, GT-mean aligned): PSNR / SSIM /
chroma_noise. A measurement; never a dependency of the package unless it wins.

    python experiments/oidn_study.py CAPTURE [--views 4] [--h-luma 0.8]
"""
from __future__ import annotations

import argparse
import sys
from typing import Dict, List

import torch

from bm3d_luma_study import capture_views
from pilot_wiener_study import print_means, score
from retinexgs.data.srgb import srgb_to_linear_extended
from retinexgs.retinex import denoise as dn


def oidn(rgb: torch.Tensor, hdr: bool) -> torch.Tensor:
    """OIDN's RT filter on ``rgb`` [H,W,3] (float32, CPU)."""
    import pyoidn
    return pyoidn.denoise(rgb.float().contiguous(), hdr=hdr, quality="high").to(rgb)


def run(lin: torch.Tensor, noise: dn.NoiseModel, h_luma: float) -> Dict[str, torch.Tensor]:
    """The candidates' linear light for one view ``lin`` [H,W,3]."""
    p = dn.DenoiseParams(h_luma=h_luma)
    x = lin.double()
    d = dn.gat_forward(x, noise.a, noise.b)
    to_ycc = lambda img: torch.einsum("ij,hwj->ihw", dn.YCC.to(img), img)  # noqa: E731
    ycc = to_ycc(d)
    sig = [max(1.0, dn._measured_sigma(c)) for c in ycc]
    h, w = ycc.shape[-2:]
    r = int(max(1, min(round(p.radius * w / 640.0), (min(h, w) - 1) // 2)))

    def finish(luma: torch.Tensor) -> torch.Tensor:
        chroma = torch.cat([dn._guided(luma[None], c[None], r, p.eps * s * s) for c, s in zip(ycc[1:], sig[1:])])
        out = torch.einsum("ij,ihw->hwj", dn.YCC.to(d), torch.cat([luma[None], chroma]))
        return dn.gat_inverse(out, noise.a, noise.b).float()

    out = {"noisy": lin.float(), "today": finish(dn._nlm_any(ycc[0], p.h_luma * sig[0], p, "opencv"))}
    scale = float(x.clamp_min(0).mean()) / 0.18
    out["oidn"] = oidn((x / scale).clamp_min(0), hdr=True).double() * scale
    lo, hi = float(d.min()), float(d.max())
    g = oidn(((d - lo) / (hi - lo)).clamp(0, 1), hdr=False).double() * (hi - lo) + lo
    out["oidn-gat"] = dn.gat_inverse(g, noise.a, noise.b).float()
    out["oidn+chroma"] = finish(to_ycc(g)[0])
    return out


def main(argv: List[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--h-luma", type=float, default=0.8)
    args = ap.parse_args(argv)
    opened = capture_views(args.capture)
    if opened is None:
        return 2
    views, spec = opened
    step = max(1, len(views) // args.views)
    rows: Dict[str, List[tuple]] = {}
    for view in views[::step][:args.views]:
        y = srgb_to_linear_extended(view.load_target().float())
        for name, lin in run(y, spec.noise, args.h_luma).items():
            score(rows, name, lin, view.paired_image)
        print(view.name, {k: f"{v[-1][0]:.2f}/{v[-1][1]:.3f}" for k, v in rows.items()}, flush=True)
    print(f"{args.capture}: {len(rows['noisy'])} views, h_luma {args.h_luma}; GT-mean PSNR / SSIM / chroma_noise")
    print_means(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
