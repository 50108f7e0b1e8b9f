"""The ``retinexgs darken`` and ``retinexgs noise`` sub-commands: the low-light sensor model of
:mod:`retinexgs.data.sensor` (darken normal-light photos into a dark capture; estimate a capture's noise)."""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Tuple

from retinexgs.errors import UserError
from retinexgs.formats import readable_formats


def _cast(text: str) -> Tuple[float, float, float]:
    try:
        gains = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three gains R,G,B such as 1.1,1,0.8, got {text!r}") from None
    if len(gains) != 3:
        raise argparse.ArgumentTypeError(f"expected three gains R,G,B such as 1.1,1,0.8, got {text!r}")
    return gains  # type: ignore[return-value]


def register(subparsers) -> None:
    """Add the ``darken`` and ``noise`` sub-commands to the CLI's sub-parsers."""
    p = subparsers.add_parser(
        "darken", help="turn normal-light photos into a dark, noisy capture (a documented sensor model)",
        description="Darken the normal-light photos of --data with a camera sensor model: exposure (and its "
                    "jitter between views), a colour cast, Poisson shot noise at --full-well electrons, Gaussian "
                    "read noise, 8-bit sRGB and JPEG (retinexgs/data/sensor.py has the equations). A scene in "
                    "LOM's layout (high/ + transforms_*.json) becomes a new scene with low/ written from high/, "
                    "ready to train and score; a plain folder of photos becomes a folder of dark photos. "
                    "OUT/sensor.json records the model, the seed and each view's exposure. Photos are read "
                    f"from {readable_formats()}; a HEIC or camera raw photo is written as .jpg (.png with "
                    "--jpeg-quality 0) under its own name, since darken cannot write those types.")
    p.add_argument("--data", required=True, type=Path, help="a scene with high/ photos, or a folder of photos")
    p.add_argument("--out", required=True, type=Path, help="the new folder (must not exist or be empty)")
    p.add_argument("--exposure", type=float, default=0.05, help="share of the light recorded, k (default 0.05)")
    p.add_argument("--exposure-jitter", type=float, default=0.1,
                   help="each view's exposure is k·(1 ± this), uniform (default 0.1)")
    p.add_argument("--full-well", type=float, default=1500.0,
                   help="electrons at full scale: fewer = more shot noise (default 1500; 0 = noise-free)")
    p.add_argument("--read-noise", type=float, default=4.0, help="read noise in electrons (default 4)")
    p.add_argument("--cast", type=_cast, default=(1.0, 1.0, 1.0), metavar="R,G,B",
                   help="channel gains of a colour cast, e.g. 0.8,1,1.25 for blue (default 1,1,1)")
    p.add_argument("--jpeg-quality", type=int, default=90, help="JPEG quality, 0 = PNG (default 90)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--raw", action="store_true",
                   help="write what a camera writes at night: OUT/raw/ with low/NAME.dng (14- or 12-bit Bayer "
                        "mosaic, black level, white balance, colour matrix, NoiseProfile, EXIF exposure) and "
                        "OUT/jpeg/, the camera's own JPEGs of the same photons (retinexgs/data/raw_sim.py)")
    p.add_argument("--bits", type=int, default=None, help="with --raw: the raw's bit depth, 12 or 14 (default 14)")
    p.add_argument("--cfa", default=None, type=str.upper,
                   help="with --raw: the Bayer pattern from the top-left pixel, RGGB, BGGR, GRBG or GBRG "
                        "(default RGGB)")
    p.add_argument("--jobs", type=int, default=None,
                   help="with --raw: worker processes, one view each at a time (default: one per CPU core; the "
                        "files are the same for any number: each view has its own random stream)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_darken)

    q = subparsers.add_parser(
        "noise", help="estimate the sensor noise of a capture from its photos",
        description="Estimate, per colour channel, the noise of the photos in --data (or its low/ folder) as "
                    "var = a·y + b in linear light (shot noise a = 1/full well, read noise b), from the photos "
                    "alone; prints the fitted full well and the noise's standard deviation at the photos' "
                    "median and 90th-percentile levels (each photo's central 1024x1024 pixels at most), and the cap "
                    "training puts on the exposed SSIM. JPEG removes part of the noise: the figures are a "
                    "lower bound of the sensor's. Camera raw files (DNG, CRW, NEF, ...): the model training "
                    "weighs their linear light by, per photo and their median, from the DNG NoiseProfile or "
                    "measured on the raw mosaic (retinexgs/data/raw_noise.py).")
    q.add_argument("--data", required=True, type=Path, help="a scene (its low/ photos) or a folder of photos")
    q.add_argument("--photos", type=int, default=None,
                   help="photos to read, spread over the capture (default: as training reads them, 8; of raw "
                        "files 5 for their noise model and 8 for the SSIM's cap)")
    q.add_argument("--share", type=float, default=None,
                   help="loss.rec_noise_share, where training places the cap (default: configs/default.yaml's)")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.set_defaults(func=_noise)


def _darken(args: argparse.Namespace) -> int:
    from retinexgs.data.sensor import SensorModel, darken_scene  # lazy: --help stays fast

    model = SensorModel(exposure=args.exposure, exposure_jitter=args.exposure_jitter,
                        full_well=args.full_well or None, read_noise=args.read_noise, cast=args.cast,
                        jpeg_quality=args.jpeg_quality)
    camera = None
    if args.raw:
        from retinexgs.data.raw_sim import RawCamera  # lazy: --help stays fast

        camera = RawCamera(bits=14 if args.bits is None else args.bits, cfa=args.cfa or "RGGB")
    elif args.bits is not None or args.cfa is not None or args.jobs is not None:
        flag = "--bits" if args.bits is not None else "--cfa" if args.cfa is not None else "--jobs"
        raise UserError(f"{flag} applies only to raw files: add --raw, or leave it out")
    report = darken_scene(args.data, args.out, model, seed=args.seed, progress=not args.quiet, raw=camera,
                          jobs=args.jobs)
    if camera is not None:
        print(f"{report.photos} dark raw photos (DNG) written to {report.out / 'raw'} and the camera's JPEGs of "
              f"the same captures to {report.out / 'jpeg'} (model and exposures in {report.out / 'sensor.json'})")
        return 0
    print(f"{report.photos} dark photos written to {report.out} (model and exposures in "
          f"{report.out / 'sensor.json'})")
    return 0


def _noise(args: argparse.Namespace) -> int:
    from retinexgs.data.images import is_raw_file, list_images, no_images_reason  # lazy: --help stays fast
    from retinexgs.run.config import load_config  # lazy: --help stays fast
    from retinexgs.train.noise import MEASURED_VIEWS, measure_capture_noise, sigma_limit  # lazy (and torch)

    folder = args.data / "low" if (args.data / "low").is_dir() else args.data
    if not folder.is_dir():
        raise UserError(f"{args.data} is not a folder")
    photos = list_images(folder)
    if not photos:
        raise UserError(f"no photos in {folder}: {no_images_reason(folder)}")
    if args.photos is not None and args.photos < 1:
        raise UserError(f"--photos must be at least 1, got {args.photos}")
    loss = load_config(["default"]).loss
    share = loss.rec_noise_share if args.share is None else args.share
    try:
        limit = sigma_limit(share)
    except ValueError:
        raise UserError(f"--share must lie between 0 and 1 (exclusive), got {share}") from None
    raws = [p for p in photos if is_raw_file(p)]
    if raws:  # a raw scene trains on its raw files (beside JPEGs too): their noise, never PIL's view of them
        return _raw_noise(args, folder, photos, raws, loss, share, limit)
    views = MEASURED_VIEWS if args.photos is None else args.photos
    # The measure training uses (train/noise.py): each photo read once, for the noise model and the SSIM's cap.
    cap = measure_capture_noise(photos, views=views, scale=loss.rec_noise_scale, through_codec=True,
                                progress=not args.quiet)
    if cap is None:
        raise UserError(f"no photo in {folder} is 8x8 pixels or larger")
    from retinexgs.train.noise import jpeg_codec  # lazy (torch)

    jpeg = jpeg_codec(photos[0]) is not None
    print(f"{folder}: {len(photos)} photos, noise from {min(views, len(photos))}, "
          + ("fitted through their own JPEG (its tables simulated; one a, b for the three channels)" if jpeg
             else "measured as they are (not JPEG)"))
    _print_model(cap.a, cap.b, photos[len(photos) // 2], lift_b=cap.at_capture()[1])
    _print_cap(cap.gain_cap(limit), limit, share)
    _print_blotches(photos)
    return 0


def _print_blotches(photos) -> None:
    """What ``decomposer.denoise: auto`` reads on these photos and decides (PhotoCapture.auto_denoise)."""
    from retinexgs.data.capture import PHOTO, PHOTO_BLOTCH_MIN  # lazy: --help stays fast
    from retinexgs.train.colour_blotches import BLOTCH_MIN_SIDE, previews_chroma_blotch  # lazy (torch)

    blotch = previews_chroma_blotch(photos)
    chosen = PHOTO.auto_denoise(lambda: blotch)
    how = ("decomposed after the chroma denoiser" if chosen != "none" else "decomposed as they are")
    print("  training (decomposer.denoise: auto): " + (
        f"photos under {BLOTCH_MIN_SIDE} px are not read for colour blotches, {how}" if blotch == 0.0 else
        f"colour noise σ {blotch:.3f} on 4x4-pixel averages ({'above' if chosen != 'none' else 'at most'} "
        f"{PHOTO_BLOTCH_MIN:g}): {how}") + " (at full resolution)")


def _print_model(a, b, median_photo: Path, lift_b=None) -> None:
    """The per-channel lines of ``noise``: var = a·y + b, the full well 1/a, black's lift (``lift_b``: the read
    noise's variance as the camera recorded it, clipped at black; None for raw values, which are not clipped) and the
    noise at the median and 90th-percentile levels of ``median_photo``."""
    import numpy as np  # lazy: --help stays fast

    from retinexgs.data.images import read_image_float  # lazy: --help stays fast
    from retinexgs.data.sensor import NoiseEstimate, clipped_moments, srgb_to_linear  # lazy: --help stays fast
    from retinexgs.train.noise import check_not_black  # lazy (and torch)

    est = NoiseEstimate(tuple(a), tuple(b), 0)  # type: ignore[arg-type]
    for name, c in zip("RGB", range(3)):
        fw = est.full_well[c]
        print(f"  {name}: full well {'inf' if math.isinf(fw) else f'{fw:.0f}'} e-, a={est.a[c]:.3g}, b={est.b[c]:.3g}")
    if lift_b is None:
        print("  black is not lifted: raw values keep the noise below black, and training fits them unclipped "
              "(loss.raw.mode)")
    else:
        # black as the camera records it on average: the mean of the read noise clipped at 0, from the photos' noise
        lift = clipped_moments(np.zeros(3), np.sqrt(np.maximum(lift_b, 0.0)))[0]
        print("  black is recorded on average at linear " + ", ".join(f"{v:.5f}" for v in lift)
              + " (R, G, B: clipped noise averages above black; the output's exposure gain multiplies it)")
    photo = read_image_float(median_photo)  # a raw file: its view, in the units of its a, b
    check_not_black(photo, median_photo)  # its levels would be 0: an SNR of 0 says nothing
    lin = srgb_to_linear(photo.astype(np.float64))
    for q in (0.5, 0.9):
        y = float(np.quantile(lin, q))
        s = est.sigma_at(y)
        print(f"  sigma at the {int(q * 100)}th-percentile level (linear {y:.4f}): "
              + ", ".join(f"{v:.5f}" for v in s) + f"  (SNR {y / max(np.mean(s), 1e-12):.1f})")


def _print_cap(g: float, limit: float, share: float) -> None:
    """What training does with the exposed photos' noise (loss.rec_noise_floor, loss.rec_noise_share)."""
    print("  training (loss.rec_noise_floor): the exposed SSIM's gain is "
          + (f"not capped (the noise stays under σ = {limit:.4f})" if math.isinf(g) else f"capped at {g:.2f}")
          + f" (loss.rec_noise_share {share:g}; at full resolution; data.downscale divides the noise)")


def _raw_noise(args: argparse.Namespace, folder: Path, photos, raws, loss, share: float, limit: float) -> int:
    """``noise`` on camera raw files: the noise model training weighs their linear light by (loss.raw.mode; the DNG
    NoiseProfile, or measured on the mosaic: retinexgs/data/raw_noise.py), per photo and the median training uses,
    in the views' linear light (1 = the raw's white at the folder's median exposure), and the SSIM's cap from the
    same views read as photos. No raw file is opened with PIL."""
    import sys

    from retinexgs.data.raw_noise import NOISE_VIEWS, combine_views, views_noise  # lazy: --help stays fast
    from retinexgs.train.noise import MEASURED_VIEWS, measure_capture_noise  # lazy (and torch)

    views = NOISE_VIEWS if args.photos is None else args.photos
    measured = views_noise(raws, views, progress=not args.quiet)
    for v in measured:
        if v.black:  # its view is all zero: train refuses it too (its decomposition)
            raise UserError(f"cannot measure the noise of {v.path}: the photo is all zero (black): there is nothing "
                            "to measure")
    cap = measure_capture_noise(raws, views=MEASURED_VIEWS if args.photos is None else args.photos,
                                scale=loss.rec_noise_scale, progress=not args.quiet)
    noise = combine_views(measured)
    for note in (noise.notes if noise is not None else [v.note for v in measured if v.note]):
        print(f"warning: {note}", file=sys.stderr)
    others = len(photos) - len(raws)
    kinds = sorted({p.suffix.lower() for p in raws})
    source = {"profile": "from their DNG NoiseProfile", "estimate": "measured on their raw mosaic",
              "mixed": "from the DNG NoiseProfile or measured on the raw mosaic"}
    print(f"{folder}: {len(raws)} camera raw photos ({', '.join(kinds)}), noise from {len(measured)} in their views' "
          f"linear light (1 = the raw's white), as training weighs them (loss.raw.mode {loss.raw.mode}), "
          + (source[noise.source] if noise is not None else "not measurable (no NoiseProfile, no flat area)")
          + (f"; the {others} other photos beside them are left out (a scene trains on its raw files)"
             if others else ""))
    for v in measured:
        if v.a is None or v.b is None:
            print(f"  {v.path.name}: no model (no usable NoiseProfile, too little flat area)")
            continue
        how = "NoiseProfile" if v.source == "profile" else "measured"
        print(f"  {v.path.name} ({how}): a = " + ", ".join(f"{x:.3g}" for x in v.a) + "; b = "
              + ", ".join(f"{x:.3g}" for x in v.b) + " (R, G, B)")
    if noise is None:
        print("  the raw views' noise could not be measured: training weighs their pixels equally")
    else:
        print(f"  the median of the {len([v for v in measured if v.a is not None])} (what training uses), "
              "var = a·y + b:")
        _print_model(noise.a, noise.b, raws[len(raws) // 2])
    if cap is None:
        raise UserError(f"no photo in {folder} is 8x8 pixels or larger")
    _print_cap(cap.gain_cap(limit), limit, share)
    return 0
