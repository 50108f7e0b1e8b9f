"""The ``train``, ``eval`` and ``demo`` sub-commands."""
from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import List, Optional

from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write_text
from retinexgs.formats import readable_formats


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="auto", help="cpu, cuda or auto (default: cuda when available)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train RetinexGS (or a baseline) on a scene",
                       description="Train on SCENE (LOM/transforms JSON, COLMAP or a folder of photos) into RUN: "
                                   "decomposes the views (cached), trains, checkpoints, then evaluates the "
                                   "test views (metrics.json, renders/test/*.png). Photos are read from "
                                   f"{readable_formats()}.")
    p.add_argument("--data", type=Path, help="scene folder (not needed with --resume; if given, it must be the "
                   "run's scene)")
    p.add_argument("--out", required=True, type=Path, help="run folder (must not exist unless --resume)")
    p.add_argument("--config", action="append", default=[],
                   help="override file or name in configs/ (e.g. ablations/no_tv); repeatable")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one key, e.g. --set steps=3000 --set loss.w_tv=0")
    p.add_argument("--resume", action="store_true",
                   help="continue RUN from its newest checkpoint; --set/--config then change the run (steps, log, "
                        "checkpoint, lr, loss, density, eval keys; recorded in RUN/config.yaml) or are refused")
    p.add_argument("--relocate-scene", action="store_true",
                   help="with --resume --data NEW: the run's scene folder was moved to NEW (its training views "
                        "must match); NEW is recorded in the run")
    p.add_argument("--view", action="store_true",
                   help="serve the scene in the web viewer while it trains (needs retinexgs[view]; see the view "
                        "command)")
    p.add_argument("--view-port", type=int, default=8080, help="port of --view (default 8080; 0 = any free one)")
    p.add_argument("--view-host", default="127.0.0.1", help="address --view binds (default 127.0.0.1)")
    p.add_argument("--min-registered", type=float, default=None, metavar="SHARE",
                   help="a folder of photos posed by SfM: refuse it when SfM registers less than this share of the "
                        "photos (default 0.5, data.min_registered; 0 accepts any model); the same as --set "
                        "data.min_registered=SHARE")
    p.add_argument("--gpus", type=int, default=None, metavar="N",
                   help="train on N GPUs of this machine, data parallel over views (N x train.views_per_rank "
                        "views a step): re-launches itself through torchrun (the same as torchrun --nproc_per_node N "
                        "-m retinexgs train ...); 1 = the plain run; with --device cpu, N CPU "
                        "processes (gloo), for testing")
    _add_common(p)
    p.set_defaults(func=_train)

    p = sub.add_parser("eval", help="re-evaluate a trained run on its test views",
                       description="Render the test views of RUN from its newest checkpoint and compare them "
                                   "with the scene's normal-light photos: rewrites RUN/metrics.json (PSNR, "
                                   "SSIM; LPIPS with eval.lpips) and the side-by-side RUN/renders/test/*.png.")
    p.add_argument("--run", required=True, type=Path, help="run folder (made by retinexgs train)")
    _add_common(p)
    p.set_defaults(func=_eval)

    p = sub.add_parser("demo", help="generate a small dark scene, train on it and report the gain (no downloads)",
                       description="Generate a small synthetic dark scene with its normal-light truth "
                                   "(OUT/scene), train RetinexGS on it with configs/demo.yaml (OUT/run), then "
                                   "report the test views' PSNR/SSIM against the truth next to the dark "
                                   "input's. One to two minutes on two CPU cores; nothing is downloaded.")
    p.add_argument("--out", type=Path, default=Path("retinexgs-demo"), help="folder for the scene and the run")
    p.add_argument("--steps", type=int, default=None, help="training steps (default: configs/demo.yaml)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier demo's scene/ and run/ at --out (anything else there is kept); "
                        "refused, naming them, while scene/ or run/ hold files the demo did not write")
    _add_common(p)
    p.set_defaults(func=_demo)


def _train(args: argparse.Namespace) -> int:
    from retinexgs.train.runner import train_run  # lazy: --help stays fast

    if args.data is None and not args.resume:
        raise UserError("--data SCENE is required (only --resume can do without it: the run knows its scene)")
    if args.min_registered is not None:  # a config key, so the run's config.yaml records it for eval and render
        args.set = [*args.set, f"data.min_registered={args.min_registered!r}"]
    if args.gpus is not None:
        code = _launch_ranks(args)
        if code is not None:
            return code
    on_trainer = None
    if args.view:  # checked before any work: a missing viser or a bad port must not cost a training run
        from retinexgs.viewer.live import live_viewer  # lazy: the viewer (viser) loads only with --view
        from retinexgs.viewer.server import check_address, import_viser  # lazy: the viewer (viser) loads only with --view
        check_address(args.view_host, args.view_port)
        import_viser()
        on_trainer = live_viewer(args.view_host, args.view_port)
    train_run(args.data, args.out, args.config, args.set, args.device, args.resume, progress=not args.quiet,
              relocate_scene=args.relocate_scene, on_trainer=on_trainer)
    return 0


def _launch_ranks(args: argparse.Namespace):
    """``train --gpus N``: torchrun's exit code after running N ranks, or None to train in this process (N = 1,
    or this process is already one of torchrun's ranks)."""
    n = args.gpus
    if n < 1:
        raise UserError(f"--gpus must be a number of GPUs >= 1, got {n}")
    world = os.environ.get("WORLD_SIZE")
    if world is not None:  # one of the ranks (torchrun given --gpus by hand): the launch is done
        if world != str(n):
            raise UserError(f"--gpus {n} inside torchrun with WORLD_SIZE={world}: give torchrun's --nproc_per_node "
                            "or --gpus, not both")
        return None
    if n == 1:
        return None
    from retinexgs.train.distributed import relaunch  # lazy: torch loads only to train

    return relaunch(n, args.device, getattr(args, "argv", sys.argv[1:]))


_EVAL_WRITES = "eval rewrites RUN/metrics.json and RUN/renders/test/"
_EVAL_FIX = "make the run folder writable, or copy the run to a writable folder and evaluate the copy"


def _eval(args: argparse.Namespace) -> int:
    from retinexgs.evaluate.evaluate import eval_run  # lazy: --help stays fast
    from retinexgs.fileio import is_out_of_space, nearest_existing, out_of_space_error, write_probe  # lazy: as above

    run = args.run
    if run.is_dir():  # checked before the model loads and the views render (a missing run: load_run says so)
        for folder in (run, run / "renders" / "test"):
            where = nearest_existing(folder)
            reason = where.is_dir() and write_probe(where)
            if reason:
                raise UserError(f"--run {run}: cannot write in {where} ({reason}): {_EVAL_WRITES}; {_EVAL_FIX}")
    try:
        eval_run(run, args.device)
    except OSError as exc:  # a write refused after the checks (a file made read-only, a mount gone read-only)
        if is_out_of_space(exc, run):
            raise out_of_space_error(exc.filename or run / "metrics.json", "") from None
        if exc.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
            raise
        name = f"{exc.filename}: " if exc.filename else ""
        raise UserError(f"--run {run}: {name}{exc.strerror or exc} ({_EVAL_WRITES}; {_EVAL_FIX})") from None
    return 0


# What `retinexgs demo` writes into its --out: only these are replaced by --overwrite. Anything else there (the
# docs/usage.md's `render --out retinexgs-demo/exposure-X` folders, the user's notes) was made by someone else: kept.
_DEMO_MADE = ("scene", "run")
# The files the demo wrote into scene/ and run/ (paths relative to --out), recorded when it ends (also after an
# error or Ctrl-C). --overwrite refuses, naming them, while anything else is in there (notes, an exported PLY,
# render's outputs): training needs an empty run/, so the user's files cannot stay where they are.
_DEMO_FILES = ".retinexgs-demo-files.json"
_DEMO_MARKERS = (".retinexgs-demo", _DEMO_FILES)
_NAMED = 5  # files named in the refusal before "and N more"


def _files_in_demo_folders(out: Path) -> List[str]:
    """Every file (and link) under ``out``'s scene/ and run/, as sorted paths relative to ``out``."""
    found = []
    for name in _DEMO_MADE:
        top = out / name
        if top.is_symlink() or top.is_file():
            found.append(name)
        elif top.is_dir():
            for folder, dirs, files in os.walk(top):  # links to folders are listed, not followed
                found += [(Path(folder) / f).relative_to(out).as_posix() for f in files]
                found += [(Path(folder) / d).relative_to(out).as_posix() for d in dirs
                          if (Path(folder) / d).is_symlink()]
    return sorted(found)


def _recorded_demo_files(out: Path) -> Optional[List[str]]:
    """The files an earlier demo recorded as its own, or None when it recorded none (stopped by a kill, or from
    before the record was kept)."""
    try:
        files = json.loads((out / _DEMO_FILES).read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return [str(f) for f in files] if isinstance(files, list) else None


def _record_demo_files(out: Path) -> None:
    """Record what this demo wrote into scene/ and run/ (see :data:`_DEMO_FILES`)."""
    atomic_write_text(out / _DEMO_FILES, json.dumps({"files": _files_in_demo_folders(out)}, indent=0))


def _clear_earlier_demo(out: Path) -> None:
    """Delete what an earlier ``retinexgs demo`` made in ``out`` (its scene and run), and nothing else: UserError,
    naming them, when scene/ or run/ hold files the demo did not write (they would go with the folders)."""
    present = _files_in_demo_folders(out)
    recorded = _recorded_demo_files(out)
    if recorded is None and present:
        raise UserError(f"{out}: the earlier demo did not record the files it wrote in scene/ and run/ (it was "
                        "killed, or ran before they were recorded), so --overwrite cannot tell them from yours: "
                        f"keep what you need elsewhere, delete {out / 'scene'} and {out / 'run'}, then run it again")
    foreign = sorted(set(present) - set(recorded or []))
    if foreign:
        more = f" and {len(foreign) - _NAMED} more" if len(foreign) > _NAMED else ""
        raise UserError(f"--overwrite would delete {len(foreign)} file(s) in {out} the demo did not write: "
                        f"{', '.join(foreign[:_NAMED])}{more}; move them out of scene/ and run/ (or delete them) "
                        "and run it again")
    kept = sorted(p.name for p in out.iterdir() if p.name not in _DEMO_MADE and p.name not in _DEMO_MARKERS)
    for name in _DEMO_MADE:
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
    (out / _DEMO_FILES).unlink(missing_ok=True)
    print(f"--overwrite: replacing the earlier demo's {' and '.join(n + '/' for n in _DEMO_MADE)} in {out}"
          + (f"; kept: {', '.join(kept)}" if kept else ""))


def _demo(args: argparse.Namespace) -> int:
    from retinexgs.demo.synthetic import make_demo_scene  # lazy: --help stays fast
    from retinexgs.run.config import load_config  # lazy: --help stays fast
    from retinexgs.train.runner import train_run  # lazy: --help stays fast

    out = args.out
    marker = out / ".retinexgs-demo"
    if args.steps is not None and args.steps < 1:  # checked before anything is written
        raise UserError(f"--steps must be a positive number of training steps, got {args.steps}")
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; the demo needs a folder (choose another --out)")
    if out.exists() and any(out.iterdir()):
        if args.overwrite and not marker.exists():
            raise UserError(f"{out} already exists and was not made by `retinexgs demo` (no {marker.name} in it); "
                            "--overwrite only replaces a folder the demo made itself: choose another --out")
        if not (args.overwrite and marker.exists()):
            raise UserError(f"{out} already exists; choose another --out"
                            + (" or pass --overwrite to replace the earlier demo" if marker.exists() else ""))
        _clear_earlier_demo(out)
    overrides = [f"steps={args.steps}"] if args.steps is not None else []
    load_config(["demo"], overrides)  # a missing or broken config fails here, before anything is written
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(marker, "made by `retinexgs demo`; safe to delete\n")  # a full disk: a UserError
    t0 = time.time()
    try:
        scene = make_demo_scene(out / "scene")
        print(f"demo scene written to {scene} ({time.time() - t0:.1f} s)")
        metrics = train_run(scene, out / "run", ["demo"], overrides, args.device, progress=not args.quiet)
    finally:  # also after an error or Ctrl-C: what is in scene/ and run/ now, the demo wrote
        with contextlib.suppress(OSError, UserError):  # unrecorded (a full disk): --overwrite then asks to clear
            _record_demo_files(out)
    if metrics:
        m = metrics["mean"]
        print(f"\nRetinexGS demo: enhanced renders PSNR {m['psnr']:.2f} dB / SSIM {m['ssim']:.3f} vs the "
              f"normal-light truth; the dark input scores {m['low_psnr']:.2f} dB / {m['low_ssim']:.3f} "
              f"(+{m['psnr'] - m['low_psnr']:.2f} dB). Total {time.time() - t0:.0f} s.")
        print(f"side-by-side images: {out / 'run' / 'renders' / 'test'}")
    return 0
