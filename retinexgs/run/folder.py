"""A run folder on disk: its recorded config and scene, the device, and the model rebuilt from the newest
checkpoint (what eval, render, export, view and resume read back)."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import torch
import yaml

from retinexgs.data import Scene, load_scene
from retinexgs.data.photo_balance import estimate_photo_balance
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write_text
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.run.checkpoint import latest_checkpoint, load_checkpoint
from retinexgs.run.config import Config, RawConfig, configs_dir, load_config, plain, read_yaml


def pick_device(device: Optional[str]) -> str:
    """``cuda`` when available unless told otherwise; a clear error for an unavailable CUDA."""
    if device in (None, "auto"):
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError("--device cuda was given but torch sees no CUDA GPU (use --device cpu)")
    if device != "cpu" and not device.startswith("cuda"):
        raise UserError(f"--device must be cpu, cuda or auto, got {device!r}")
    return device


def open_scene(path: Path, cfg: Config, cache_hint: str = "--set data.cache_dir=DIR") -> Scene:
    """Load the scene as a run's config says (reader, downscale, caches); train and decompose share it so
    that they read the same (undistorted, downscaled) images. ``cache_hint``: the caller's spelling of
    ``data.cache_dir`` for the message when the scene folder is read-only."""
    d = cfg.data
    scene = load_scene(path, reader=d.reader, downscale=d.downscale,
                       cache_dir=d.cache_dir and Path(d.cache_dir) / "scene", cache_hint=cache_hint,
                       sfm_options=dict(min_registered=d.min_registered))
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
                           cfg.method == "retinexgs", raw=scene.raw)
    model.load_state_dict(state["model"])
    model.to(pick_device(device))
    return cfg, scene, model, int(state["step"])


# Keys whose default changed after they were added: a run made before the key existed behaved as the value here,
# not as today's default (which would re-render it differently). The tone form was the gamma on L̂ until
# 2026-11-25, when the exposure tone became the default; the depth prior came in later that day, at weight 0.3
# in the default (a run made before it, resumed, must not start using it); the reconstruction term was on the
# dark photo's values (rec_domain photo) until the exposed SSIM became the default, later still; renders were over
# black until the mean background became the default (2026-11-26), and blind to the capture's noise until
# issue 32 (the noise floor of the exposed SSIM, the camera's clipped noise). The exposure meter averaged until
# the highlight cap (2026-11-27), and a batch of views stepped with torch's Adam betas until β^B (the same day).
# Density events ran to density.stop until density.last_event capped them. A raw scene's priors weighed
# every pixel alike until loss.rec_raw_prior_snr (2026-11-28), and renders drew Gaussians up to 0.01 from the
# camera until model.near_fraction (the same day). A raw scene's tone took the photos' highlight knee until
# model.enhancement.shoulder_raw (the same day), and its L_spa read the unclipped target until loss.spa_raw.
# A folder posed by SfM was used whatever share of its photos SfM registered until data.min_registered.
# This table is the one place for these
# values: the code reads every key from the validated config, with no fallback of its own.
PREDATING_VALUES: Dict[str, Any] = {"model.enhancement.tone": "illumination", "loss.w_depth": 0.0,
                                    "loss.rec_domain": "photo", "model.background": "black",
                                    "model.enhancement.shoulder": 1.0, "loss.rec_noise_floor": False,
                                    "loss.rec_camera_noise": False, "loss.rec_noise_share": 0.5,
                                    "density.noise_aware": False, "loss.rec_noise_scale": 1,
                                    "loss.exp_highlight_share": 0.0, "train.momentum_batch_scaling": "none",
                                    "density.last_event": 1.0, "loss.rec_raw": "photo",
                                    "decomposer.raw_denoise": False, "loss.rec_raw_unit": "plain",
                                    "loss.rec_raw_prior_snr": 0.0, "model.near_fraction": 0.0,
                                    "model.enhancement.shoulder_raw": None, "loss.spa_raw": "extended",
                                    "data.min_registered": 0.0}


def _fill_missing(cfg: RawConfig, default: RawConfig, prefix: str, filled: List[str]) -> RawConfig:
    """Keys added to default.yaml after the run was made get the behaviour the run had: the value in
    :data:`PREDATING_VALUES` where the default changed since, else their default (a run folder outlives versions)."""
    out = dict(cfg)
    for key, value in default.items():
        if key not in out:
            out[key] = copy.deepcopy(PREDATING_VALUES.get(prefix + key, value))
            filled.append(prefix + key)
        elif isinstance(value, dict) and isinstance(out[key], dict) and key != "params":
            out[key] = _fill_missing(out[key], value, f"{prefix}{key}.", filled)
    return out


def read_run_config(run_dir: Path, log: Optional[Callable[[str], None]] = None) -> Tuple[Config, Path]:
    """(validated config, scene path) recorded in ``run_dir/config.yaml``."""
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise UserError(f"{run_dir} is not a run folder (no config.yaml)")
    raw = read_yaml(path)
    scene = raw.pop("scene", None)
    if not isinstance(scene, str):
        raise UserError(f"{path} does not name the run's scene (key 'scene'); it is not a RetinexGS run config")
    filled: List[str] = []
    raw = _fill_missing(raw, read_yaml(configs_dir() / "default.yaml"), "", filled)
    if filled and log is not None:
        log(f"{path} predates config keys {', '.join(filled)}: using the values that match how it was trained")
    return load_config(base=raw, base_label=str(path)), Path(scene)


def write_run_config(run: Path, cfg: Config, scene_path: Path) -> None:
    """The resolved config of a run (what resume, eval, render and export read back), written as plain data."""
    data = plain(cfg)
    data["scene"] = str(Path(scene_path).resolve())
    atomic_write_text(run / "config.yaml", yaml.safe_dump(data, sort_keys=False))
