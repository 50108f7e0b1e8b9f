"""The ``retinexgs`` command line: one entry point, one sub-command per stage.

Each stage module exposes ``register(subparsers)`` which adds its sub-command(s) and sets ``func`` on the
parsed namespace. Errors meant for the user are raised as :class:`retinexgs.errors.UserError` and printed
as one paragraph with a non-zero exit code, never as a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading
from pathlib import Path
from typing import List, Optional

from retinexgs import __version__
from retinexgs.errors import Terminated, UserError
from retinexgs.fileio import missing_folders, remove_empty_trees
from retinexgs.openmp import bound_openmp_spinning

# Before any sub-command imports torch (they do so lazily): idle OpenMP threads spin briefly, then sleep.
bound_openmp_spinning()

# Stage modules that contribute sub-commands, in the order ``--help`` lists them.
_COMMAND_MODULES = [
    "retinexgs.commands.train",
    "retinexgs.commands.decompose",
    "retinexgs.commands.frames",
    "retinexgs.commands.sfm",
    "retinexgs.commands.sensor",
    "retinexgs.commands.render",
    "retinexgs.commands.export",
    "retinexgs.commands.view",
    "retinexgs.commands.bench",
]


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every available sub-command."""
    parser = argparse.ArgumentParser(
        prog="retinexgs",
        description="RetinexGS: normally-lit, 3D-consistent novel views from multi-view photos taken in the "
                    "dark. One sub-command per stage, each with its own --help.")
    # The version of the installed package: retinexgs.__version__, which setup.py reads (one source).
    parser.add_argument("--version", action="version", version=f"retinexgs {__version__}",
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:  # stage not present in this build
                continue
            raise
        module.register(sub)
    return parser


def _raise_terminated(signum, frame) -> None:
    # A second SIGTERM during the clean-up ends the process at once.
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    raise Terminated()


def _rank_note() -> str:
    """Under torchrun with several ranks: which rank this is, and why it may have been stopped."""
    world, rank = os.environ.get("WORLD_SIZE", ""), os.environ.get("RANK", "")
    if not world.isdigit() or int(world) < 2:
        return ""
    return (f" (rank {rank} of {world}: torchrun stops every rank once one fails; the failed rank's error is "
            "printed above or in torchrun's summary)")


def main(argv: Optional[List[str]] = None) -> int:
    """Run the command line; returns the process exit code (2 for a UserError, 130 after Ctrl-C, 143 after
    SIGTERM: both stop through the same clean-up, never a stack dump)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    args.argv = list(sys.argv[1:] if argv is None else argv)  # as given (train --gpus re-launches with them)
    # The folders the command's path arguments would create (the outermost missing one of each): a command that
    # fails removes those it left empty (a full disk's --out new/a/b.ply), never a folder that existed before.
    fresh = missing_folders(v for v in vars(args).values() if isinstance(v, Path))
    restore = None
    if threading.current_thread() is threading.main_thread():
        restore = signal.signal(signal.SIGTERM, _raise_terminated)
    code = 1  # an unexpected exception (a bug) counts as a failure too
    try:
        code = int(args.func(args) or 0)
        return code
    except UserError as exc:
        print(f"retinexgs {args.command}: error: {exc}", file=sys.stderr)
        code = 2
        return 2
    except Terminated:
        print(f"retinexgs {args.command}: terminated{_rank_note()}", file=sys.stderr)
        code = 143
        return 143
    except KeyboardInterrupt:
        print(f"retinexgs {args.command}: interrupted", file=sys.stderr)
        code = 130
        return 130
    finally:
        if code != 0:
            remove_empty_trees(fresh)
        if restore is not None:  # main() called in-process (tests): leave the caller's handler as it was
            signal.signal(signal.SIGTERM, restore)


if __name__ == "__main__":
    sys.exit(main())
