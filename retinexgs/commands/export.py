"""The ``export`` sub-command: a trained run as a standard 3DGS PLY."""
from __future__ import annotations

import argparse
from pathlib import Path

from retinexgs.commands.common import add_run_options
from retinexgs.export import DEFAULT_DIRECTIONS


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``export`` sub-command to the CLI's sub-parsers."""
    p = sub.add_parser("export", help="export a trained run as a standard 3DGS PLY (enhancement baked in)",
                       description="Write RUN's Gaussians to an INRIA 3DGS PLY in the input's world frame, with "
                                   "the illumination and enhancement baked into the SH colours by a least-squares "
                                   "fit over view directions (or R̂ alone with --reflectance-only).")
    add_run_options(p)
    p.add_argument("--out", required=True, type=Path, help="the .ply file to write")
    p.add_argument("--reflectance-only", action="store_true", help="export R̂'s SH without illumination")
    p.add_argument("--directions", type=int, default=DEFAULT_DIRECTIONS,
                   help=f"view directions of the SH fit (default {DEFAULT_DIRECTIONS})")
    p.add_argument("--white-balance", default="as-trained", metavar="WB",
                   help="a white-balance edit baked into the colours, in linear light before the highlight shoulder "
                        "and the sRGB curve (as render --white-balance): as-trained (default), auto (grey-edge), "
                        "gains:R,G,B, temp:KELVIN[,TINT] (6504 = as trained; higher = warmer) or pick:VIEW,X,Y "
                        "(that pixel of that view's render is neutral); recorded in the PLY's colour comment")
    p.set_defaults(func=_export)


def _export(args: argparse.Namespace) -> int:
    from retinexgs.export.export import export_run  # lazy: --help stays fast

    export_run(args.run, args.out, args.reflectance_only, args.directions, args.exposure, args.gamma,
               args.device, args.force, progress=not args.quiet, white_balance=args.white_balance)
    return 0
