"""Run-folder rules checked before any expensive work: a writable ``--out``, one trainer per run folder (a lock),
and what ``--resume`` may change (config overrides applied and recorded, or refused by name; ``--data``
checked against the run's scene)."""
from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, Optional, Sequence, Tuple, Union

from retinexgs.errors import UserError
from retinexgs.fileio import TMP_PREFIX, check_writable_folder  # noqa: F401 (re-exported for runner)
from retinexgs.config import Config, RawConfig, plain
from retinexgs.run.config import load_config

# Keys a resumed run may change: they act from the next step on (the run's length, its logging and
# checkpointing, learning rates, loss weights, the density and SH schedules, evaluation, the cache folder).
# Every other key fixes the model's structure or what the run trains (method, seed, data, decomposer, model)
# and is refused on --resume.
RESUMABLE: Tuple[str, ...] = ("steps", "log", "checkpoint", "lr", "loss", "density", "eval", "train",
                              "model.sh_degree_every", "data.cache_dir")


# ---- --out --------------------------------------------------------------------------------------------------

def is_empty_run_folder(path: Path) -> bool:
    """No files other than the temporaries of an interrupted atomic write."""
    return not path.exists() or all(p.name.startswith(TMP_PREFIX) for p in path.iterdir())


# ---- one trainer per run folder -----------------------------------------------------------------------------

@contextlib.contextmanager
def run_lock(run_dir: Path) -> Iterator[None]:
    """Hold an exclusive lock on the run folder itself (flock on the folder, so nothing is written): a second
    trainer on the same run is refused. The OS releases it when the process exits or is killed."""
    fd = os.open(run_dir, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UserError(f"run folder {run_dir} is in use by another trainer (it holds the folder's lock); "
                            "wait for it to finish or stop it, or choose another --out") from None
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


# ---- the config of a resumed run ----------------------------------------------------------------------------

def _leaves(cfg: RawConfig, prefix: str = "") -> Dict[str, Any]:
    out: Dict[str, Any] = {}
    for key, value in cfg.items():
        if isinstance(value, dict) and key != "params":
            out.update(_leaves(value, f"{prefix}{key}."))
        else:
            out[prefix + key] = value
    return out


def changed_keys(old: Union[Config, RawConfig], new: Union[Config, RawConfig]) -> Dict[str, Tuple[Any, Any]]:
    """key path -> (old value, new value) for every key whose value differs (typed or plain configs, compared
    as data)."""
    a, b = _leaves(plain(old)), _leaves(plain(new))
    return {k: (a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)}


def resume_config(recorded: Config, files: Sequence[str], overrides: Sequence[str], run_dir: Path,
                  checkpoint_step: int) -> Tuple[Config, Dict[str, Tuple[Any, Any]]]:
    """The recorded config with ``--config``/``--set`` applied, and what changed; refuses the keys that a
    resumed run cannot change (by name) and a ``steps`` below the step already trained."""
    cfg = load_config(files, overrides, base=recorded, base_label=str(Path(run_dir) / "config.yaml"))
    changes = changed_keys(recorded, cfg)
    fixed = [k for k in changes if not any(k == r or k.startswith(r + ".") for r in RESUMABLE)]
    if fixed:
        k = fixed[0]
        more = f" (and {', '.join(fixed[1:])})" if len(fixed) > 1 else ""
        raise UserError(f"--resume cannot change {k}{more}: the run {run_dir} was made with {k}="
                        f"{changes[k][0]!r}, asked {changes[k][1]!r}; it fixes the model's structure or what the "
                        f"run trains, so start a new run (another --out). A resume may change: "
                        f"{', '.join(RESUMABLE)}")
    if "steps" in changes and cfg.steps < checkpoint_step:
        raise UserError(f"--resume: steps={cfg.steps} is below the step the run {run_dir} has already "
                        f"trained ({checkpoint_step}); give steps >= {checkpoint_step}")
    return cfg, changes


# ---- the scene of a resumed run -----------------------------------------------------------------------------

def resume_scene(recorded: Path, given: Optional[Path], relocate: bool, run_dir: Path) -> Tuple[Path, bool]:
    """(scene path to use, whether it moves the run to a new scene folder). ``--data`` must be the recorded
    scene unless ``--relocate-scene`` says the scene folder was moved."""
    if given is None:
        if relocate:
            raise UserError("--relocate-scene needs --data NEW_SCENE_FOLDER (where the run's scene now is)")
        if not Path(recorded).exists():
            raise UserError(f"the scene of run {run_dir}, {recorded}, does not exist; if the scene folder was "
                            "moved, pass --data NEW_FOLDER --relocate-scene")
        return recorded, False
    if Path(given).resolve() == Path(recorded).resolve():
        return recorded, False
    if not relocate:
        raise UserError(f"--data {given} is not the scene the run {run_dir} was trained on ({recorded}); "
                        "resume without --data, or pass --relocate-scene to point the run at its moved scene "
                        "folder (its training views are checked to match)")
    return Path(given), True


def check_same_views(recorded: Optional[Iterable[str]], names: Iterable[str], old: Path, new: Path) -> bool:
    """A relocated scene must have the training views the run was trained on (same count and file names);
    False when the run has no record of them to compare with (checkpoints older than the record)."""
    if recorded is None:
        return False
    recorded, names = sorted(recorded), sorted(names)
    if recorded != names:
        missing = sorted(set(recorded) - set(names))
        extra = sorted(set(names) - set(recorded))
        detail = "; ".join(x for x in (f"missing {', '.join(missing[:3])}" if missing else "",
                                       f"not in the run {', '.join(extra[:3])}" if extra else "") if x)
        raise UserError(f"--relocate-scene: {new} has {len(names)} training views, the run was trained on "
                        f"{len(recorded)} from {old} ({detail}); it is not the same scene")
    return True
