"""Checks shared by ``render`` and ``export``: run config, enhancement flags, output overwrites."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Iterable, Optional

from retinexgs.errors import UserError
from retinexgs.run import folder
from retinexgs.config.schema import Config


def read_run_config(run_dir: Path) -> Config:
    """The run's saved config (validated, as :func:`retinexgs.run.folder.load_run` reads it), read before the
    (slower) model and scene load so flags fail fast."""
    return folder.read_run_config(Path(run_dir))[0]


def check_enhancement_flags(cfg: Config, run_dir: Path, exposure: Optional[float], gamma: Optional[float]) -> None:
    """``--exposure`` / ``--gamma`` need a RetinexGS run (the baselines have no illumination to re-expose)."""
    if exposure is None and gamma is None:
        return
    flag = "--exposure" if exposure is not None else "--gamma"
    if exposure is not None and gamma is not None:
        raise UserError("--exposure adjusts the predicted gamma and --gamma replaces it: give one of them")
    if cfg.method != "retinexgs":
        raise UserError(f"{flag} needs a RetinexGS run, but {run_dir} was trained with method="
                        f"{cfg.method} (a plain-3DGS baseline has no illumination or gamma to change)")
    value = exposure if exposure is not None else gamma
    if not (value > 0 and math.isfinite(value)):
        raise UserError(f"{flag} must be a positive finite number, got {value}")


def refuse_existing(paths: Iterable[Path], force: bool) -> None:
    """Refuse to overwrite existing outputs unless ``force``: name the first one (and count the rest)."""
    existing = [p for p in paths if Path(p).exists()]
    for p in existing:  # first: --force would not help (it replaces files, never a folder)
        if Path(p).is_dir():
            raise UserError(f"{p} is a folder; --out must name a file here")
    if existing and not force:
        more = f" (and {len(existing) - 1} more output files)" if len(existing) > 1 else ""
        raise UserError(f"{existing[0]} already exists{more}; pass --force to overwrite, or choose another --out")
