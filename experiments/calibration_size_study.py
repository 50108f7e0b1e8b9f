"""How the denoiser's calibrated noise estimate depends on the photo's size (issue 64;
notes/2026-11-29-adam-one-launch.md §5).

A clean photo (a normal-light view: its own noise is far below what is added) is resized to a width W (area
averaging), darkened by ``--scale`` in linear light, given Poisson-Gaussian noise of a known model (var = a·y + b), and
stabilised with that model (the generalised Anscombe transform, unit noise); then each luma/chroma component's σ is
measured as ``decomposer.denoise`` calibrates it (``retinexgs.retinex.denoise._measured_sigma``: Immerkær on 4×4
averages, × 4). The true σ is 1: above it is texture read as noise. One RESULT line per width.

    python experiments/calibration_size_study.py PHOTO [PHOTO ...] --widths 640,320,160,96 --seeds 3
"""
import argparse
import json
import math

import numpy as np
import torch
import torch.nn.functional as F

from retinexgs.data.images import read_image_float
from retinexgs.data.srgb import srgb_to_linear
from retinexgs.retinex.denoise import YCC, _measured_sigma, gat_forward


def median_sigma(x: torch.Tensor, scale: int = 4) -> float:
    """The same measurement with the median of |response| (Immerkær's robust form, as losses.noise_variance): a
    Gaussian's median |r| is 0.6745 σ; edges and texture, a minority of the samples, move it little."""
    if min(x.shape) < 3 * scale:
        scale = 1
    y = F.avg_pool2d(x[None, None], scale)[0, 0] if scale > 1 else x
    k = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], dtype=y.dtype)
    c = F.conv2d(y[None, None], k[None, None])[0, 0]
    return float(c.abs().median() / (0.6745 * 6.0)) * scale


def pca_sigma(x: torch.Tensor, scale: int = 4, patch: int = 5) -> float:
    """σ at ``scale``×``scale`` averages as the square root of the smallest eigenvalue of the covariance of all
    ``patch``×``patch`` patches (Liu, Tanaka & Okutomi 2013 without their weak-texture selection): texture lives in a
    few principal directions of the patches, white noise in all of them alike."""
    if min(x.shape) < 3 * scale:
        scale = 1
    y = F.avg_pool2d(x[None, None], scale)[0, 0] if scale > 1 else x
    cols = F.unfold(y[None, None], patch)[0].T  # [patches, patch²]
    cols = cols - cols.mean(0, keepdim=True)
    cov = cols.T @ cols / max(1, cols.shape[0] - 1)
    return float(torch.linalg.eigvalsh(cov)[0].clamp_min(0).sqrt()) * scale


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("photos", nargs="+")
    p.add_argument("--widths", default="640,320,160,96")
    p.add_argument("--scale", type=float, default=0.05, help="the darkening, linear light")
    p.add_argument("--a", type=float, default=2e-4, help="shot-noise factor of the model")
    p.add_argument("--b", type=float, default=4e-6, help="read-noise variance of the model")
    p.add_argument("--seeds", type=int, default=3)
    args = p.parse_args()
    a, b = [args.a] * 3, [args.b] * 3
    for width in [int(w) for w in args.widths.split(",")]:
        rows = []
        for path in args.photos:
            img = torch.from_numpy(read_image_float(path)).double()
            lin = srgb_to_linear(img) * args.scale
            h = round(lin.shape[0] * width / lin.shape[1])
            small = F.interpolate(lin.permute(2, 0, 1)[None], size=(h, width), mode="area")[0].permute(1, 2, 0)
            for seed in range(args.seeds):
                g = torch.Generator().manual_seed(seed)
                noisy = small + torch.randn(small.shape, generator=g, dtype=torch.float64) * (
                    args.a * small.clamp_min(0) + args.b).sqrt()
                d = gat_forward(noisy, a, b)
                ycc = torch.einsum("ij,hwj->ihw", YCC.to(d), d)
                clean = torch.einsum("ij,hwj->ihw", YCC.to(d), gat_forward(small, a, b))
                rows.append([_measured_sigma(c) for c in ycc] + [_measured_sigma(c) for c in clean]
                            + [median_sigma(c) for c in ycc] + [median_sigma(c) for c in clean]
                            + [pca_sigma(c) for c in ycc] + [pca_sigma(c) for c in clean])
        m = np.array(rows)
        print("RESULT " + json.dumps({"width": width, "noisy_luma_chroma": m[:, :3].mean(0).round(3).tolist(),
                                      "clean_luma_chroma": m[:, 3:6].mean(0).round(3).tolist(),
                                      "median_noisy": m[:, 6:9].mean(0).round(3).tolist(),
                                      "median_clean": m[:, 9:12].mean(0).round(3).tolist(),
                                      "pca_noisy": m[:, 12:15].mean(0).round(3).tolist(),
                                      "pca_clean": m[:, 15:].mean(0).round(3).tolist(), "n": len(rows)}))


if __name__ == "__main__":
    main()
