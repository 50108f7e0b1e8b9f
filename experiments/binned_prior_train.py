"""Train with the 2D priors denoised on 2×2-binned views, upsampled back (issue 64): a study, not a package option.

At half size (``data.downscale=2``) the R prior's luma pays (κ 1 beat κ 0 by ~1 dB on fox-dark and fountain-dark,
[r-prior-chroma §7](notes/2026-11-30-r-prior-chroma.md)), at full size it does not: a likely reason is that binning
leaves the single-view denoiser a finer noise it removes well, where the full-size demosaiced noise is coarse. Can a
full-size run have both, the priors from the binned view and the reconstruction from the full-size one? This runs
``python -m retinexgs ARGS`` in this process after replacing ``retinexgs.retinex.denoise.denoise_linear`` (which
makes the priors' photo) by: the view 2×2-averaged, denoised there at the average's noise (÷ 4) with the config's
settings at full strength, bilinearly upsampled to the view's size; its cache entries get their own version.

    python experiments/binned_prior_train.py -- train --data CAPTURE --out RUN [--set loss.raw.r_prior_luma=1 ...]
"""
from __future__ import annotations

import sys

import torch
import torch.nn.functional as F


def patch() -> None:
    """Make the priors' denoiser run on the 2×2-binned view (see the module docstring)."""
    from retinexgs.retinex import denoise as dn

    plain = dn.denoise_linear

    def binned(lin, noise, method, params=None, backend="auto", device=None):
        if method == "none" or lin.dim() != 3 or min(lin.shape[:2]) < 8:
            return plain(lin, noise, method, params, backend, device)
        h, w = lin.shape[:2]
        small = F.avg_pool2d(lin.permute(2, 0, 1)[None].float(), 2)[0].permute(1, 2, 0)
        quarter = dn.NoiseModel(tuple(a / 4 for a in noise.a), tuple(b / 4 for b in noise.b))
        out = plain(small.to(lin.dtype), quarter, method, dn.DenoiseParams(), backend, device)
        up = F.interpolate(out.permute(2, 0, 1)[None].float(), size=(h, w), mode="bilinear", align_corners=False)
        return up[0].permute(1, 2, 0).to(out.dtype)

    dn.denoise_linear = binned
    dn.DENOISE_VERSION = "1+binned2"


def main() -> int:
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    patch()
    from retinexgs.cli import main as cli_main

    sys.argv = ["retinexgs", *argv[split + 1:]]
    return cli_main()


if __name__ == "__main__":
    sys.exit(main())
