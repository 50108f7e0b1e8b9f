"""Train a noisy raw capture with its 2D priors made from the noise-free capture of the same scene (issue 64): a
study, not a package option.

How much could a better single-view denoiser still give? The priors (LR3M of the denoised view) are the one place a
denoiser acts; an oracle that denoises perfectly gives the priors of the clean view, at the same exposure. This runs
``python -m retinexgs ARGS`` in this process after replacing the priors' reader
(``retinexgs.retinex.cache.read_image``) for every view that has a twin of the same name under ``--clean``'s
``low/`` (the raw ladder's ``clean`` level of the same scene: same exposures, no noise): the twin, white-balanced as
the noisy view would be and encoded as the denoiser's output is (linear light clipped to [0, 1], sRGB), instead of
the noisy view through the denoiser. The training views, their noise model and the reconstruction stay the noisy
capture's. Give the run its own ``--set data.cache_dir=DIR``: the oracle's priors are cached under the noisy views'
keys, and must not mix with the real ones.

    python experiments/oracle_prior_train.py --clean CLEAN_CAPTURE --downscale D --cache-dir DIR -- train \\
        --data CAPTURE --out RUN --set data.downscale=D --set data.cache_dir=DIR [--set ...]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _stem(path: Path) -> str:
    """A view's name: ``0008`` for ``low/0008.dng`` and for its undistorted, downscaled copy ``0008-<digest>.npy``."""
    return Path(path).stem.split("-")[0]


def patch(clean: Path, downscale: float, cache_dir: Path) -> None:
    """Make the priors' reader return the clean twin of each noisy view (see the module docstring). The clean
    capture is loaded as training loads the noisy one (``downscale``, ``cache_dir``), so a twin is undistorted and
    resized alike."""
    from retinexgs.data.images import holds_unclipped, load_image_tensor
    from retinexgs.data.load import load_scene
    from retinexgs.data.photo_balance import balance_photo
    from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear, srgb_to_linear_extended
    from retinexgs.retinex import cache

    real = cache.read_image
    if not (clean / "low").is_dir():
        raise SystemExit(f"{clean} has no low/ folder: give the raw ladder's clean capture of the same scene")
    from retinexgs.errors import UserError
    try:
        scene = load_scene(clean, downscale=downscale, cache_dir=cache_dir)
    except UserError as exc:  # one line, as the CLI gives it
        raise SystemExit(f"--clean {clean}: {exc}") from None
    twins = {_stem(v.image_path): Path(v.image_path) for v in scene.views}

    def oracle(path, raw_denoise=False, balance=None, denoise=None, cache_root=None, cache_hint=""):
        twin = twins.get(_stem(Path(path)))
        if twin is None:
            return real(path, raw_denoise, balance, denoise, cache_root, cache_hint)
        raw = holds_unclipped(twin)
        image = balance_photo(load_image_tensor(twin, unclipped=raw), balance, unclipped=raw).float()
        lin = srgb_to_linear_extended(image) if raw else srgb_to_linear(image)
        return linear_to_srgb(lin.clamp(0.0, 1.0)).float().contiguous()

    cache.read_image = oracle


def main() -> int:
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clean", type=Path, required=True, help="the noise-free capture of the same scene")
    ap.add_argument("--downscale", type=float, default=1.0, help="the training's data.downscale")
    ap.add_argument("--cache-dir", type=Path, required=True, help="the training's data.cache_dir")
    args = ap.parse_args(argv[:split])
    patch(args.clean, args.downscale, args.cache_dir)
    from retinexgs.cli import main as cli_main

    sys.argv = ["retinexgs", *argv[split + 1:]]
    return cli_main()


if __name__ == "__main__":
    sys.exit(main())
