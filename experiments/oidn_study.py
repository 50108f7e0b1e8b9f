"""Would Intel Open Image Denoise (a pretrained, Apache-2.0 network) make better priors than today's NLM on a night
view? (issue 64 item 1)

Every classical denoiser tried on fox-dark at 1000 e⁻ lost the detail the fit needs (NLM, BM3D, FFDNet:
experiments/notes/2026-11-30-bm3d-luma.md); priors from the noise-free capture lift the trained SSIM from 0.74 to
0.88 (r-prior-chroma §4-5). OIDN is a U-Net trained on rendering noise and shipped with its weights (`pip install
pyoidn`: MIT binding, OIDN Apache-2.0, CPU and CUDA devices). Its premise, measured on single views as
bm3d_luma_study.py does: ``--views`` training views of a capture, evenly spaced, through

- ``today``: ``decomposer.denoise``'s ``chroma`` at ``--h-luma``;
- ``oidn``: OIDN (HDR, quality high) on the view's linear light;
- ``oidn-gat``: OIDN (LDR) on the variance-stabilised view (GAT at the measured noise), scaled into [0, 1], inverted;
- ``oidn+chroma``: OIDN's luma, today's luma-guided chroma filter (in the GAT domain);
- ``oidn-binK``: OIDN (HDR) on the view's K×K means (K = 2, 3, 4: a whiter noise), bilinearly upsampled;
- ``oidn-albedo``: OIDN (HDR) given today's denoised view as a clean albedo (``clean_aux``);

scored against the view's normal-light truth (exposed to a mean luma of 0.18, sRGB, GT-mean aligned): PSNR / SSIM /
chroma_noise. A measurement; never a dependency of the package unless it wins.

    python experiments/oidn_study.py CAPTURE [--views 4] [--h-luma 0.8]
"""
from __future__ import annotations

import sys
from typing import Dict, List, Optional

import torch
import torch.nn.functional as F

from bm3d_luma_study import sampled_views, stabilised, study_parser
from pilot_wiener_study import print_means, score
from retinexgs.retinex import denoise as dn


def oidn(rgb: torch.Tensor, hdr: bool, albedo: Optional[torch.Tensor] = None) -> torch.Tensor:
    """OIDN's RT filter on ``rgb`` [H,W,3] (float32, CPU); ``albedo``: a clean one in [0, 1]."""
    try:
        import pyoidn
    except ImportError:
        raise SystemExit("this study needs pyoidn (pip install pyoidn; Apache-2.0, an 88 MB wheel)") from None
    aux = None if albedo is None else albedo.float().contiguous()
    return pyoidn.denoise(rgb.float().contiguous(), aux, hdr=hdr, clean_aux=aux is not None, quality="high").to(rgb)


def run(lin: torch.Tensor, noise: dn.NoiseModel, h_luma: float) -> Dict[str, torch.Tensor]:
    """The candidates' linear light for one view ``lin`` [H,W,3]."""
    x = lin.double()
    d, _, _, finish, luma_today = stabilised(lin, noise, h_luma)
    out = {"noisy": lin.float(), "today": finish(luma_today)}
    scale = float(x.clamp_min(0).mean()) / 0.18
    out["oidn"] = oidn((x / scale).clamp_min(0), hdr=True).double() * scale
    lo, hi = float(d.min()), float(d.max())
    g = oidn(((d - lo) / (hi - lo)).clamp(0, 1), hdr=False).double() * (hi - lo) + lo
    out["oidn-gat"] = dn.gat_inverse(g, noise.a, noise.b).float()
    out["oidn+chroma"] = finish(torch.einsum("ij,hwj->ihw", dn.YCC.to(g), g)[0])
    hdr = (x / scale).clamp_min(0).permute(2, 0, 1)[None]
    for k in (2, 3, 4):
        small = oidn(F.avg_pool2d(hdr, k)[0].permute(1, 2, 0), hdr=True).permute(2, 0, 1)[None]
        up = F.interpolate(small, size=x.shape[:2], mode="bilinear", align_corners=False)
        out[f"oidn-bin{k}"] = up[0].permute(1, 2, 0) * scale
    clean = out["today"].double().clamp_min(0) / scale
    out["oidn-albedo"] = oidn(hdr[0].permute(1, 2, 0), hdr=True, albedo=(clean / clean.max()).clamp(0, 1)) * scale
    return out


def main(argv: List[str]) -> int:
    args = study_parser(__doc__).parse_args(argv)
    sampled = sampled_views(args.capture, args.views)
    if sampled is None:
        return 2
    rows: Dict[str, List[tuple]] = {}
    for view, y in sampled[0]:
        for name, lin in run(y, sampled[1], args.h_luma).items():
            score(rows, name, lin, view.paired_image)
        print(view.name, {k: f"{v[-1][0]:.2f}/{v[-1][1]:.3f}" for k, v in rows.items()}, flush=True)
    print(f"{args.capture}: {len(rows['noisy'])} views, h_luma {args.h_luma}; GT-mean PSNR / SSIM / chroma_noise")
    print_means(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
