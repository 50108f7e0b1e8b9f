"""Train with the night priors' luma from BM3D instead of NLM (issue 64 item 1): a study, not a package option.

[bm3d_luma_study.py](bm3d_luma_study.py) found BM3D's luma a little better than today's NLM on single views at full
strength (1.5× the calibrated σ) and worse at fox-dark's light strength; a single view's score does not predict the
trained result, so this trains with it. It runs ``python -m retinexgs ARGS`` in this process after replacing the
luma filter of ``decomposer.denoise: chroma`` (``retinexgs.retinex.denoise._nlm_any``, which that method calls for
the luma alone) by BM3D at ``--scale`` × the component's calibrated σ (as ``_filter`` measures it), whatever
``h_luma`` the scene's view count sets, and giving the denoiser's cache entries their own version so that no
NLM entry is reused. BM3D is the Tampere reference package (`pip install bm3d`, non-commercial use only): a
measurement, never a dependency.

    python experiments/bm3d_prior_train.py --scale 1.5 -- train --data CAPTURE --out RUN [--set ...]
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import torch


def load_bm3d():
    """The bm3d module, or SystemExit with one line where it is not installed."""
    try:
        import bm3d
    except ImportError:
        raise SystemExit("this study needs the bm3d package (pip install bm3d; non-commercial licence)") from None
    if not hasattr(np, "trapz"):  # bm4d 4.2.5 (under bm3d) calls numpy 1's name
        np.trapz = np.trapezoid
    return bm3d


def patch(scale: float) -> None:
    """Make ``decomposer.denoise: chroma`` filter the luma with BM3D at ``scale`` × its calibrated σ."""
    from retinexgs.retinex import denoise as dn

    bm3d = load_bm3d()

    def luma_bm3d(x: torch.Tensor, h: float, p, impl: str) -> torch.Tensor:
        sigma = max(1.0, dn._measured_sigma(x)) if p.calibrate else 1.0
        y = x.detach().cpu().double().numpy()
        out = np.asarray(bm3d.bm3d(y, sigma * scale)).reshape(y.shape)
        return torch.from_numpy(out).to(x)

    dn._nlm_any = luma_bm3d
    dn.DENOISE_VERSION = f"1+bm3d{scale:g}"


def main() -> int:
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.5)
    args = ap.parse_args(argv[:split])
    patch(args.scale)
    from retinexgs.cli import main as cli_main

    sys.argv = ["retinexgs", *argv[split + 1:]]
    return cli_main()


if __name__ == "__main__":
    sys.exit(main())
