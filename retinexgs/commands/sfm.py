"""The ``retinexgs sfm`` sub-command: structure-from-motion on a folder of photos."""
from __future__ import annotations

import argparse
import sys


def register(subparsers) -> None:
    """Add the ``sfm`` sub-command to the CLI's sub-parsers."""
    p = subparsers.add_parser(
        "sfm", help="estimate camera poses and sparse points from a folder of photos (pycolmap)",
        description="Run structure-from-motion on the photos in --images and cache the COLMAP model in "
                    "--out/sparse/0. Dark photos are brightened and denoised for feature extraction.")
    p.add_argument("--images", required=True, help="folder of photos (not searched recursively)")
    p.add_argument("--out", default=None,
                   help="output folder (default: <scene>/retinexgs_sfm, the scene being the photo folder, "
                        "or its parent when the folder is named images/); COLMAP files already there that "
                        "retinexgs sfm did not make are kept unless --force")
    p.add_argument("--matching", choices=["auto", "exhaustive", "sequential"], default="auto",
                   help="pair selection: exhaustive up to 100 photos, else sequential (default: auto)")
    p.add_argument("--enhance", choices=["auto", "on", "off"], default="auto",
                   help="brighten+denoise before feature extraction: auto = only for dark folders")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL",
                   help="COLMAP camera model: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL (default), RADIAL, OPENCV "
                        "or FULL_OPENCV")
    p.add_argument("--max-features", type=int, default=8192, help="SIFT features per photo (default 8192)")
    p.add_argument("--threads", type=int, default=-1, help="CPU threads (default: all)")
    p.add_argument("--force", action="store_true",
                   help="recompute even when a cached model matches, and replace COLMAP files (database.db, "
                        "sparse/0) in --out that retinexgs sfm did not make (without it they are refused)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run SfM for parsed ``args`` and print a summary; returns the exit code."""
    from retinexgs.data.sfm import run_sfm  # lazy: --help stays fast

    enhance = {"auto": "auto", "on": True, "off": False}[args.enhance]
    result = run_sfm(args.images, args.out, matching=args.matching, enhance=enhance,
                     camera_model=args.camera_model, max_num_features=args.max_features,
                     num_threads=args.threads, force=args.force,
                     progress=None if args.quiet else (lambda m: print(f"[sfm] {m}", file=sys.stderr,
                                                                         flush=True)))
    print(f"registered views: {result.num_registered}/{result.num_images}")
    print(f"points: {result.num_points}")
    print(f"model: {result.model_dir}")
    print(f"time: {result.seconds:.1f} s{' (cached)' if result.cached else ''}"
          f"{', features from enhanced copies' if result.enhanced else ''}")
    return 0 if result.num_registered > 0 else 1
