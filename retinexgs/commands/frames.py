"""The ``retinexgs frames`` sub-command: photos for a scene from a (phone) video, the sharpest frame of each
equal time interval (:mod:`retinexgs.data.video`)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

# Kept in step with retinexgs.data.video (not imported here: --help stays fast, without numpy).
_DEFAULT_MAX = 60
_DEFAULT_FLOOR = 0.5


def register(subparsers) -> None:
    """Add the ``frames`` sub-command to the CLI's sub-parsers."""
    p = subparsers.add_parser(
        "frames", help="photos from a video: the sharpest frame of each time interval, as PNG",
        description="Decode --video (any video ffmpeg reads: a phone's MP4/MOV), split it into equal time "
                    "intervals and write the sharpest frame of each into --out as a lossless 8-bit PNG named by "
                    "its time in the video (frame_000012.345s.png, so the names sort by time). Sharpness is the "
                    "variance of the Laplacian of the luma, downscaled and lightly blurred first so that a dark "
                    "video's noise does not count as detail; black frames are never picked. Then "
                    "'retinexgs sfm --images OUT' and 'retinexgs train --data OUT' use the folder as any folder "
                    "of photos.")
    p.add_argument("--video", required=True, type=Path, help="the video file")
    p.add_argument("--out", required=True, type=Path,
                   help="folder for the frames: new or empty (see --overwrite)")
    p.add_argument("--max", type=int, default=None, metavar="N",
                   help=f"number of intervals, so at most N frames (default {_DEFAULT_MAX}; with --every, a cap)")
    p.add_argument("--every", type=float, default=None, metavar="SECONDS",
                   help="one interval (one frame) per SECONDS of video instead of a fixed number")
    p.add_argument("--sharpness-floor", type=float, default=_DEFAULT_FLOOR, metavar="F",
                   help=f"leave out an interval whose sharpest frame scores below F x the video's median frame: "
                        f"it is all motion blur (default {_DEFAULT_FLOOR}; 0 keeps every interval)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty --out: replaces (and removes) only the frames an earlier "
                        "retinexgs frames wrote there; every other file is kept")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Extract the frames for parsed ``args`` and print a summary; returns the exit code."""
    from retinexgs.data.video import extract_frames  # lazy: --help stays fast

    state: dict = {}  # the scoring bar, while it is shown

    def say(msg: str) -> None:
        if "t" in state:  # the scoring bar is done once a line is said
            state.pop("t").close()
        if not args.quiet:
            print(f"[frames] {msg}", file=sys.stderr, flush=True)

    def bar(done: int, expected: int) -> None:
        """The scoring pass's progress bar (the pass that decodes every frame)."""
        if args.quiet:
            return
        if "t" not in state:
            from tqdm import tqdm

            state["t"] = tqdm(total=expected or None, desc="[frames] scoring", unit="frame", file=sys.stderr,
                              leave=True)  # its last line stays: an error after it starts a line of its own
        t = state["t"]
        t.update(done - t.n)

    try:
        result = extract_frames(args.video, args.out, max_frames=args.max, every=args.every,
                                floor=args.sharpness_floor, overwrite=args.overwrite, progress=say, bar=bar)
    finally:
        if "t" in state:
            state.pop("t").close()
    if result.removed:
        say(f"--overwrite: removed {len(result.removed)} earlier frames of ours not picked this time")
    if result.kept:
        shown = ", ".join(result.kept[:5]) + (" ..." if len(result.kept) > 5 else "")
        say(f"kept what else --out holds: {shown}")
    if result.left_out:
        spans = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in result.left_out[:6])
        more = f" and {len(result.left_out) - 6} more" if len(result.left_out) > 6 else ""
        say(f"{len(result.left_out)} of {result.num_intervals} intervals had no frame sharp enough, left out: "
            f"{spans}{more}")
    print(f"frames: {len(result.written)} of {result.num_intervals} intervals "
          f"({result.num_decoded} frames decoded at {result.fps:g} fps)")
    print(f"folder: {result.out_dir}")
    print(f"next: retinexgs sfm --images {result.out_dir}")
    return 0
