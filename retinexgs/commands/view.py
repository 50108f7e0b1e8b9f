"""The ``view`` sub-command."""
from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="look around a trained run in the browser (needs retinexgs[view])",
                       description="Serve a web viewer (viser) of RUN: orbit the scene from the browser and switch "
                                   "maps (enhanced, R̂, L̂, low, depth), exposure, absolute gamma and resolution "
                                   "live; set the white balance (as trained, auto, temperature/tint or R,G,B "
                                   "gains, and 'Pick a neutral': the next click on the view makes that pixel "
                                   "grey; the same edit as render --white-balance) and turn the highlight "
                                   "shoulder off; snap to the training and test cameras. Binds 127.0.0.1 unless "
                                   "--host says otherwise. Stop with Ctrl-C.")
    p.add_argument("--run", required=True, type=Path, help="a trained run folder")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; the next free one when taken; 0 = any)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--device", default="auto", help="cpu, cuda or auto (default: cuda when available)")
    p.set_defaults(func=_view)


def _view(args: argparse.Namespace) -> int:
    from retinexgs.viewer.server import view_run  # lazy: the viewer (viser) loads only with --view

    view_run(args.run, args.host, args.port, args.device)
    return 0
