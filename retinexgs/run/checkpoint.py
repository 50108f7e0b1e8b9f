"""Atomic checkpoints in ``RUN/checkpoints/step_XXXXX.pt`` (temporary file + rename; never a partial file), each
carrying the run format it was written in and read back migrated to this version's
(:func:`retinexgs.config.migrate_checkpoint`).

A save interrupted by a kill leaves at worst a hidden ``.step_XXXXX.pt.*.tmp``: never listed or loaded, and
removed by the run's next save (one run folder has one trainer at a time)."""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Dict, List, Optional

import torch

from retinexgs.config import FORMAT, migrate_checkpoint
from retinexgs.errors import UserError
from retinexgs.fileio import (default_file_mode, is_out_of_space, out_of_space_error, remove_empty_folders,
                              temporary_file)

_PATTERN = re.compile(r"step_(\d+)\.pt$")
_TEMP_PATTERN = re.compile(r"^\.step_\d+\.pt\..*\.tmp$")  # what atomic_save leaves when killed mid-write


def checkpoint_dir(run: Path) -> Path:
    return Path(run) / "checkpoints"


def list_checkpoints(run: Path) -> List[Path]:
    """Complete checkpoints of a run, oldest first."""
    d = checkpoint_dir(run)
    if not d.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in d.iterdir() if (m := _PATTERN.search(p.name))]
    return [p for _, p in sorted(found)]


def atomic_save(obj: Any, path: Path) -> None:
    """torch.save to a temporary file in the same folder, fsync, then rename over ``path`` (with the permissions of
    every other output, 0666 minus the umask). On failure the folders it made are removed again while empty."""
    path = Path(path)
    try:
        fd, tmp, made = temporary_file(path.parent, f".{path.name}.", ".tmp")
    except OSError as exc:
        if is_out_of_space(exc, path.parent):
            raise out_of_space_error(path) from None
        raise
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, default_file_mode())  # as every other output: the umask's, not mkstemp's 0600
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        remove_empty_folders(made)  # a first checkpoint that failed leaves no empty checkpoints/ behind
        # a full disk: torch's zip writer says "unexpected pos ..." / "file write failed" (not ENOSPC)
        if isinstance(exc, Exception) and is_out_of_space(exc, path.parent):
            raise out_of_space_error(path) from None
        raise


def save_checkpoint(run: Path, step: int, state: Dict[str, Any], keep: int = 2) -> Path:
    """Write ``step_XXXXX.pt`` atomically (with the run format) and delete all but the newest ``keep`` checkpoints."""
    path = checkpoint_dir(run) / f"step_{step:06d}.pt"
    atomic_save({"format": FORMAT, **state}, path)
    for old in list_checkpoints(run)[:-keep] if keep > 0 else []:
        old.unlink(missing_ok=True)
    for stale in checkpoint_dir(run).iterdir():  # temporaries of a save interrupted by a kill (never listed)
        if _TEMP_PATTERN.match(stale.name):
            stale.unlink(missing_ok=True)
    return path


def load_checkpoint(path: Path, map_location: str = "cpu") -> Dict[str, Any]:
    """Load a checkpoint, migrated from the format it was written in to this version's; an error that names the file
    when it is unreadable or truncated, or written by a newer version."""
    try:
        state = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:  # truncated zip, wrong format, ...
        raise UserError(f"checkpoint {path} is unreadable ({type(exc).__name__}: {exc}); delete it to fall back "
                        "to the previous one") from exc
    if not isinstance(state, dict) or "step" not in state or "model" not in state:
        raise UserError(f"checkpoint {path} is not a RetinexGS checkpoint")
    return migrate_checkpoint(state, f"checkpoint {path}")


def latest_checkpoint(run: Path) -> Optional[Path]:
    found = list_checkpoints(run)
    return found[-1] if found else None
