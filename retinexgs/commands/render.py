"""The ``render`` sub-command: a trained run's views, or a camera path, to PNG / MP4."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from retinexgs.commands.common import add_run_options
from retinexgs.errors import UserError

MAX_FRAMES = 100_000  # 55 minutes at 30 fps; a path of more frames is a typo (it would build silently for minutes)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``render`` sub-command to the CLI's sub-parsers."""
    p = sub.add_parser("render", help="render a trained run's views or a camera path to PNG/MP4/EXR",
                       description="Render the enhanced image (and on request R̂, L̂, depth and the low-light "
                                   "reconstruction) of RUN's test, train or val views to OUT/<map>/<view>.png, or "
                                   "along a smooth camera path to an MP4. Existing files are kept unless --force.")
    add_run_options(p)
    # No argparse choices for --views/--path/--format: a bad value then exits through UserError (code 2,
    # one paragraph) like every other input problem, and nothing is loaded first.
    p.add_argument("--views", default=None, help="test (default), train, val (when the scene has a val split), or path (a camera path; see --path)")
    p.add_argument("--out", type=Path,
                   help="views and --format png/exr: a folder (a name ending in .mp4, or in an image file's "
                        "suffix such as .exr or .png, is refused); a path video: a .mp4 file, or a folder to write "
                        "path_<kind>.mp4 into. Default RUN/renders/<views> or RUN/renders/path_<kind>.mp4")
    p.add_argument("--maps", default="enhanced",
                   help="comma-separated: enhanced,R,L,L_raw,depth,low (default enhanced). L is the illumination "
                        "normalised for viewing, L̂/L_ref clipped to [0,1] with one scene-wide L_ref (as eval's "
                        "side-by-side and the viewer show it); L_raw is L̂ as rendered (dark)")
    p.add_argument("--path", default=None,
                   help="camera path (implies --views path): orbit (a full circle around the scene; for a "
                        "front-facing capture an ellipse within the training cameras' spread), orbit-360 (always "
                        "the full circle) or interpolate (through the training cameras)")
    p.add_argument("--frames", type=int, default=120,
                   help=f"frames of the path (default 120, at most {MAX_FRAMES})")
    p.add_argument("--fps", type=float, default=30.0, help="frames per second of the video (default 30)")
    p.add_argument("--format", default="mp4",
                   help="mp4 (default; for views: PNG), png, exr or png,exr. exr writes scene-linear float32 "
                        "OpenEXR (Rec.709 primaries; needs pip install \"retinexgs[hdr]\") to "
                        "OUT/<map>/<name>.exr: enhanced is the linear light before the highlight shoulder and "
                        "the sRGB curve, on a scale where 1.0 is the PNG's white at the chosen exposure (the "
                        "default exposure's white; brighter light is kept above 1); R is lin(R̂), L is "
                        "lin(L̂)/lin(L_ref) (1.0 = the scene's full light), L_raw lin(L̂), low lin(R̂·L̂); lin "
                        "decodes sRGB. depth has no EXR form")
    p.add_argument("--white-balance", default="as-trained", metavar="WB",
                   help="a white-balance edit of the enhanced image, in linear light before the highlight shoulder "
                        "and the sRGB curve (PNG, EXR and MP4); a neutral's green is kept. as-trained (default), "
                        "auto (grey-edge over the training views' renders), gains:R,G,B (divided by G; R/G and B/G "
                        "within 1/512..512), "
                        "temp:KELVIN[,TINT] (KELVIN 1000..40000 is the light the scene is taken to be lit by, "
                        "adapted to 6504 K, the trained scene's neutral: higher is warmer; TINT -100..100, + "
                        "magenta), or pick:VIEW,X,Y (pixel column X, row Y of view VIEW, e.g. 0001, is made grey). "
                        "The numbers used are recorded in the PNG text and EXR header")
    p.set_defaults(func=_render)


def check_frames_and_fps(frames: int, fps: float) -> None:
    """UserError for --frames outside 1..MAX_FRAMES or an --fps that is not a positive finite number."""
    if frames < 1:
        raise UserError(f"--frames must be at least 1, got {frames}")
    if frames > MAX_FRAMES:
        raise UserError(f"--frames {frames} is too many: at most {MAX_FRAMES} (55 minutes of video at 30 fps, "
                        "already hours to render); render a long video in parts")
    if not (math.isfinite(fps) and fps > 0):
        raise UserError(f"--fps must be a positive finite number of frames per second, got {fps:g}")


def _render(args: argparse.Namespace) -> int:
    from retinexgs.export.renders import parse_maps, render_run  # lazy: --help stays fast

    check_frames_and_fps(args.frames, args.fps)  # before the run loads: 10^8 frames used to build for minutes
    render_run(args.run, args.views, args.out, parse_maps(args.maps), args.exposure, args.gamma, args.path,
               args.frames, args.fps, args.format, args.device, args.force, progress=not args.quiet,
               white_balance=args.white_balance)
    return 0
