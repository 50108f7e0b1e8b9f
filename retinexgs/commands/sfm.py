"""The ``retinexgs sfm`` sub-command: structure-from-motion on a folder of photos."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from retinexgs.formats import readable_formats


def register(subparsers) -> None:
    """Add the ``sfm`` sub-command to the CLI's sub-parsers."""
    p = subparsers.add_parser(
        "sfm", help="estimate camera poses and sparse points from a folder of photos (pycolmap)",
        description="Run structure-from-motion on the photos in --images and cache the COLMAP model in "
                    "--out/sparse/0. Dark photos are brightened and denoised for feature extraction. Photos "
                    f"are read from {readable_formats()}.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", help="folder of photos (not searched recursively)")
    src.add_argument("--video", type=Path,
                     help="a video instead of photos: its sharpest frame per interval (as retinexgs frames does, "
                          "at most 60) goes to SCENE/images first, SCENE being the video's path without its "
                          "extension (clips/night.mp4: clips/night); then retinexgs train --data SCENE")
    p.add_argument("--out", default=None,
                   help="output folder (default: <scene>/retinexgs_sfm, the scene being the photo folder, "
                        "or its parent when the folder is named images/); COLMAP files already there that "
                        "retinexgs sfm did not make are kept unless --force")
    p.add_argument("--matching", choices=["auto", "exhaustive", "sequential"], default="auto",
                   help="pair selection: exhaustive up to 100 photos, else sequential (default: auto)")
    p.add_argument("--enhance", choices=["auto", "on", "off"], default="auto",
                   help="brighten+denoise before feature extraction: auto = only for dark folders")
    p.add_argument("--denoise", choices=["auto", "none", "nlm", "chroma"], default="auto",
                   help="denoise the brightened previews of dark photos and raw files first, under their measured "
                        "noise (at night the brightened noise buries the features): auto (default) = chroma where "
                        "the brightened previews' noise is high (σ > 0.08) and can be measured, none otherwise")
    p.add_argument("--night", choices=["auto", "on", "off"], default="auto",
                   help="SIFT and mapper settings for night previews (no upsampled octave, pooled descriptors, "
                        "30 inliers at 8 degrees to start a model, 10 within 4 px to add a photo, two-view points kept: "
                        "night pairs hold 30-50 inliers): auto (default) "
                        "= where the previews are denoised; off = COLMAP's own")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL",
                   help="COLMAP camera model: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL (default), RADIAL, OPENCV "
                        "or FULL_OPENCV")
    p.add_argument("--max-features", type=int, default=8192, help="SIFT features per photo (default 8192)")
    p.add_argument("--threads", type=int, default=-1, help="CPU threads (default: all)")
    p.add_argument("--force", action="store_true",
                   help="recompute even when a cached model matches, and replace COLMAP files (database.db, "
                        "sparse/0) in --out that retinexgs sfm did not make (without it they are refused)")
    p.add_argument("--min-registered", type=float, default=None, metavar="SHARE",
                   help="refuse the model when SfM registers less than this share of the photos (default 0.5; 0 "
                        "accepts any model; the photos left out are named either way)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run SfM for parsed ``args`` and print a summary; returns the exit code."""
    from retinexgs.data.sfm import MIN_REGISTERED_SHARE, run_sfm  # lazy: --help stays fast
    from retinexgs.train.sfm_preview import sfm_preview_denoise

    say = None if args.quiet else (lambda m: print(f"[sfm] {m}", file=sys.stderr, flush=True))
    images = args.images if args.video is None else _frames_from_video(args.video, say)
    enhance = {"auto": "auto", "on": True, "off": False}[args.enhance]
    denoise = sfm_preview_denoise(images, args.denoise, enhance, say)
    result = run_sfm(images, args.out, matching=args.matching, enhance=enhance, denoise=denoise, night=args.night,
                     camera_model=args.camera_model, max_num_features=args.max_features,
                     num_threads=args.threads, force=args.force,
                     min_registered=MIN_REGISTERED_SHARE if args.min_registered is None else args.min_registered,
                     progress=say)
    print(f"registered views: {result.num_registered}/{result.num_images}")
    print(f"points: {result.num_points}")
    print(f"model: {result.model_dir}")
    print(f"time: {result.seconds:.1f} s{' (cached)' if result.cached else ''}"
          f"{', features from enhanced copies' if result.enhanced else ''}")
    return 0 if result.num_registered > 0 else 1


def _frames_from_video(video: Path, say) -> Path:
    """``sfm --video``: the video's frames in SCENE/images (made by retinexgs frames' defaults, or those an
    earlier call made from the same video); returns that folder."""
    from retinexgs.data.video import check_video_file, extract_frames, frames_made_from
    from retinexgs.errors import UserError

    video = check_video_file(video)
    # A video without an extension would share its path with the scene folder.
    scene = video.with_suffix("") if video.suffix else video.with_name(video.name + "-scene")
    images = scene / "images"
    if frames_made_from(images, video):
        if say:
            say(f"using the frames of {video.name} already in {images}")
        return images
    if images.is_dir() and any(images.iterdir()):
        raise UserError(f"sfm --video writes the frames of {video} into {images}, which already holds other files: "
                        f"make the frames yourself with retinexgs frames --video {video} --out DIR, then run "
                        f"retinexgs sfm --images DIR")
    extract_frames(video, images, progress=say)
    return images
