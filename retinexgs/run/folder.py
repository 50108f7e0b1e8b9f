"""A run folder on disk: its recorded config and scene, the device, and the model rebuilt from the newest
checkpoint (what eval, render, export, view and resume read back)."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Tuple

import torch
import yaml

from retinexgs.data import Scene, load_scene
from retinexgs.data.sfm import PreviewDenoise
from retinexgs.data.photo_balance import estimate_photo_balance
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write_text
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.run.checkpoint import latest_checkpoint, load_checkpoint
from retinexgs.config import FORMAT, Config, migrate_config, plain, read_yaml
from retinexgs.run.config import load_config


def pick_device(device: Optional[str]) -> str:
    """``cuda`` when available unless told otherwise; a clear error for an unavailable CUDA."""
    if device in (None, "auto"):
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError("--device cuda was given but torch sees no CUDA GPU (use --device cpu)")
    if device != "cpu" and not device.startswith("cuda"):
        raise UserError(f"--device must be cpu, cuda or auto, got {device!r}")
    return device


def open_scene(path: Path, cfg: Config, cache_hint: str = "--set data.cache_dir=DIR",
               sfm_denoise: Optional[Callable[[Path], Optional[PreviewDenoise]]] = None) -> Scene:
    """Load the scene as a run's config says (reader, downscale, caches); train and decompose share it so
    that they read the same (undistorted, downscaled) images. ``cache_hint``: the caller's spelling of
    ``data.cache_dir`` for the message when the scene folder is read-only. ``sfm_denoise``: the previews'
    denoiser of a bare folder's SfM (``data.sfm_denoise``, from
    :func:`retinexgs.train.sfm_preview.scene_sfm_denoise`: train and decompose pass it); without it (a finished
    run read back) a denoised run takes the SfM model its training cached, whichever recipe made it."""
    d = cfg.data
    sfm_options = dict(min_registered=d.min_registered)
    if sfm_denoise is None and d.sfm_denoise != "none":
        sfm_options["denoise_cached"] = True
    scene = load_scene(path, reader=d.reader, downscale=d.downscale,
                       cache_dir=d.cache_dir and Path(d.cache_dir) / "scene", cache_hint=cache_hint,
                       sfm_options=sfm_options, sfm_denoise=sfm_denoise)
    if d.white_balance == "grey-edge":  # one balance for the capture, from its training photos (deterministic)
        gains = estimate_photo_balance([v.image_path for v in scene.train])
        for v in [*scene.train, *scene.test, *scene.val]:
            v.balance = gains
    return scene


def load_run(run_dir: Path, device: Optional[str] = None) -> Tuple[Config, Scene, RetinexGSModel, int]:
    """(config, scene, model on device, step) of a saved run, from its newest checkpoint."""
    run_dir = Path(run_dir)
    if not (run_dir / "config.yaml").is_file():
        raise UserError(f"{run_dir} is not a run folder (no config.yaml)")
    ckpt = latest_checkpoint(run_dir)
    if ckpt is None:
        raise UserError(f"run folder {run_dir} has no checkpoint (checkpoints/step_*.pt); train it first")
    cfg, scene_path = read_run_config(run_dir)
    if not Path(scene_path).is_dir():  # the run folder outlives its scene's location: say how to re-point it
        raise UserError(f"the scene of run {run_dir}, {scene_path}, does not exist (recorded in {run_dir / 'config.yaml'}); "
                        f"if it moved, point the run at it once with `retinexgs train --out {run_dir} --resume "
                        "--data NEW_SCENE --relocate-scene`")
    state = load_checkpoint(ckpt)
    gstate = {k[len("gaussians."):]: v for k, v in state["model"].items() if k.startswith("gaussians.")}
    scene = open_scene(scene_path, cfg)
    model = RetinexGSModel(GaussianModel.empty_like_state(gstate, cfg.model.sh_degree), cfg.model,
                           cfg.method == "retinexgs", scene.capture)
    model.load_state_dict(state["model"])
    model.to(pick_device(device))
    return cfg, scene, model, int(state["step"])


def read_run_config(run_dir: Path, log: Optional[Callable[[str], None]] = None) -> Tuple[Config, Path]:
    """(validated config, scene path) recorded in ``run_dir/config.yaml``, migrated from the format it was
    written in (:mod:`retinexgs.config.versions`); ``log`` hears which keys the recorded config lacked."""
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise UserError(f"{run_dir} is not a run folder (no config.yaml)")
    raw = read_yaml(path)
    scene = raw.pop("scene", None)
    if not isinstance(scene, str):
        raise UserError(f"{path} does not name the run's scene (key 'scene'); it is not a RetinexGS run config")
    raw, filled = migrate_config(raw, str(path))
    if filled and log is not None:
        log(f"{path} predates config keys {', '.join(filled)}: using the values that match how it was trained")
    return load_config(base=raw, base_label=str(path)), Path(scene)


def write_run_config(run: Path, cfg: Config, scene_path: Path) -> None:
    """The resolved config of a run (what resume, eval, render and export read back), written as plain data
    with the run format first."""
    data = {"format": FORMAT, **plain(cfg), "scene": str(Path(scene_path).resolve())}
    atomic_write_text(run / "config.yaml", yaml.safe_dump(data, sort_keys=False))
