"""Does a raw view's linear term fitted on its mosaic samples, not on their bilinear demosaic, recover detail? (issue 64)

A raw view reaches training demosaiced (bilinear, :func:`retinexgs.data.camera_raw._demosaiced_srgb_linear`): at
each pixel two of its three colours are interpolated from neighbours, and the camera -> sRGB matrix then mixes the
channels. So the linear term (:func:`retinexgs.train.losses.linear_reconstruction`) compares the render with values
that are blurred (a noise-free bilinear demosaic of fox-dark's truth scores SSIM 0.94-0.96 against it), whose noise is
correlated between neighbours and between channels, and which count three values a pixel where one was measured.
Fitted on the mosaic instead, each pixel is one independent sample with the sensor's own noise, and the views,
whose colour filters fall on different points of the scene, demosaic one another through the 3D model (RawNeRF's
argument). Here the render's linear sRGB x is taken back to white-balanced camera RGB, M x (M the inverse of the
camera -> sRGB matrix), and compared only in the channel the pixel's filter measured:

    L_lin = sum_p w_p (g (M x - M y)_{c(p)})^2 / (H W),   w_p = 1 / var_c(p)(M x) normalised to mean 1,
    var_c(v) = wb_c a_c v + wb_c^2 b_c  (the DNG's NoiseProfile (a, b) of a normalised sample, wb the white balance)

M y at the pixel's own channel is exactly the sample (times wb / the view's exposure factor): a bilinear demosaic keeps
the samples it has. The exposure factor (0.9-1.1 between a capture's views) is left out of the weights (they are
normalised per view). Everything else is today's (the SSIM term still sees the demosaiced view; the priors too).
It patches the eager loss, so train with ``--set train.cuda_graphs=false`` (``--control`` runs the same without
the patch, the comparison's other arm):

    python experiments/mosaic_loss_train.py CAPTURE [--control] -- train --data CAPTURE --out RUN --device cuda \\
        --set seed=0 --set train.cuda_graphs=false
    python experiments/mosaic_loss_train.py CAPTURE --check    # the mosaic identity above on the first DNG
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from retinexgs.data.camera_raw import folder_exposure, noise_from_profile, normalised_mosaic, read_raw, read_view_linear
from retinexgs.train import losses


def first_raw(capture: Path) -> Path:
    if not (capture / "low").is_dir():
        raise SystemExit(f"{capture} has no low/ folder of DNGs (a raw ladder capture)")
    files = sorted(p for p in (capture / "low").iterdir() if p.suffix.lower() == ".dng")
    if not files:
        raise SystemExit(f"{capture}/low has no .dng files")
    return files[0]


def camera_of(capture: Path):
    """(M [3,3] linear sRGB -> wb camera RGB, cfa [2,2], wb [3], (a, b) [3] each) of the capture's first DNG."""
    photo = read_raw(first_raw(capture))
    ab = noise_from_profile(photo)
    if ab is None:
        raise SystemExit(f"{photo.path} has no NoiseProfile")
    return (np.linalg.inv(photo.cam_to_srgb.astype(np.float64)), photo.cfa, photo.white_balance.astype(np.float64),
            ab)


def check(capture: Path) -> int:
    """M · (the view's linear sRGB) at each pixel's own channel against wb · sample / factor."""
    path = first_raw(capture)
    m, cfa, wb, _ = camera_of(capture)
    photo = read_raw(path)
    factor = folder_exposure(path.parent).factors.get(path.name, 1.0)
    cam = read_view_linear(path).astype(np.float64) @ m.T
    x = normalised_mosaic(photo).astype(np.float64)
    worst = 0.0
    for i in range(2):
        for j in range(2):
            c = int(cfa[i, j])
            got = cam[i::2, j::2, c]
            want = wb[c] * x[i::2, j::2] / factor
            worst = max(worst, float(np.abs(got - want).max() / (np.abs(want).max() + 1e-12)))
    print(f"{path.name}: largest relative difference {worst:.2e} (factor {factor:.4f})")
    return 0 if worst < 1e-4 else 1


def patch(capture: Path) -> None:
    m, cfa, wb, (a, b) = camera_of(capture)
    original = losses.linear_reconstruction
    cache = {}

    def mosaic_mask(h: int, w: int, device, dtype) -> torch.Tensor:
        key = (h, w, device, dtype)
        if key not in cache:
            mask = torch.zeros(1, 3, h, w, dtype=dtype)
            for i in range(2):
                for j in range(2):
                    mask[0, int(cfa[i, j]), i::2, j::2] = 1.0
            cache[key] = mask.to(device)
        return cache[key]

    def linear_reconstruction(rec, S, target, gain=None):
        if target.unit != "plain" or target.mode != "noise":
            return original(rec, S, target, gain)
        x, y = losses.to_linear(rec, "open"), losses.to_linear(S, "extended")
        g = target.gain if target.gain is not None else gain
        g = rec.new_ones(()) if g is None else g
        mt = torch.as_tensor(m, dtype=x.dtype, device=x.device)
        xc = torch.einsum("ij,bjhw->bihw", mt, x)
        yc = torch.einsum("ij,bjhw->bihw", mt, y)
        mask = mosaic_mask(x.shape[2], x.shape[3], x.device, x.dtype)
        with torch.no_grad():
            aa = torch.as_tensor(wb * a, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
            bb = torch.as_tensor(wb ** 2 * b, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
            w = mask / ((aa * xc.clamp_min(0.0) + bb) * g ** 2)
            w = w * (mask.sum() / w.sum(dim=(1, 2, 3), keepdim=True))
        n = x.shape[0] * x.shape[2] * x.shape[3]
        return (w * (g * (xc - yc)) ** 2).sum() / n

    losses.linear_reconstruction = linear_reconstruction


def main() -> int:
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("capture", type=Path)
    parser.add_argument("--control", action="store_true", help="train without the patch")
    parser.add_argument("--check", action="store_true", help="check the mosaic identity and exit")
    args = parser.parse_args(argv[:split])
    if args.check:
        return check(args.capture)
    if not args.control:
        patch(args.capture)
    from retinexgs.cli import main as cli
    return cli(argv[split + 1:])


if __name__ == "__main__":
    sys.exit(main())
