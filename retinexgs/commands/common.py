"""Options shared by the commands that read a trained run (render, export)."""
from __future__ import annotations

import argparse
from pathlib import Path


def add_run_options(p: argparse.ArgumentParser) -> None:
    """--run, --device, --force, --quiet and the exposure edit (--exposure or --gamma)."""
    p.add_argument("--run", required=True, type=Path, help="a trained run folder")
    p.add_argument("--device", default="auto", help="cpu, cuda or auto (default: cuda when available)")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--exposure", type=float, metavar="X",
                   help="brighten (< 1) or darken (> 1) the predicted exposure: the light / X with the default "
                        "tone (0.5 = one stop brighter), the gamma × X with the gamma tones")
    g.add_argument("--gamma", type=float, help="use this gamma instead of the predicted one")
