"""Run folders: create, train, resume, reload and evaluate (what the train / eval / demo commands call)."""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable, Dict, Iterable, Optional, Tuple, Union

import torch

from retinexgs.data import Scene, View, load_scene
from retinexgs.errors import UserError
from retinexgs.evaluate.evaluate import evaluate
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.inference import InferenceRenderer
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.render import Camera
from retinexgs.train.checkpoint import latest_checkpoint, load_checkpoint
from retinexgs.train.config import load_config
from retinexgs.train.resume import (check_same_views, check_writable_folder, is_empty_run_folder, read_run_config,
                                    resume_config, resume_scene, run_lock)
from retinexgs.train.schedule import build_schedule
from retinexgs.train.trainer import Trainer, active_sh_degree, view_camera, write_run_config


def pick_device(device: Optional[str]) -> str:
    """``cuda`` when available unless told otherwise; a clear error for an unavailable CUDA."""
    if device in (None, "auto"):
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError("--device cuda was given but torch sees no CUDA GPU (use --device cpu)")
    if device != "cpu" and not device.startswith("cuda"):
        raise UserError(f"--device must be cpu, cuda or auto, got {device!r}")
    return device


def open_scene(path: Path, cfg: Dict, cache_hint: str = "--set data.cache_dir=DIR") -> Scene:
    """Load the scene as a run's config says (reader, downscale, caches); train and decompose share it so
    that they read the same (undistorted, downscaled) images. ``cache_hint``: the caller's spelling of
    ``data.cache_dir`` for the message when the scene folder is read-only."""
    d = cfg["data"]
    return load_scene(path, reader=d["reader"], downscale=d["downscale"],
                      cache_dir=d["cache_dir"] and Path(d["cache_dir"]) / "scene", cache_hint=cache_hint)


def _checkpoint_step(run_dir: Path) -> int:
    ckpt = latest_checkpoint(run_dir)
    return int(ckpt.stem.split("_")[-1]) if ckpt is not None else 0


def train_run(scene_path: Optional[Path], run_dir: Path, config_files: Iterable[str] = (),
              overrides: Iterable[str] = (), device: Optional[str] = None, resume: bool = False,
              progress: bool = True, log: Callable[[str], None] = print,
              relocate_scene: bool = False, view: Optional[Tuple[str, int]] = None) -> Optional[Dict]:
    """Train (or resume) a run and evaluate it; returns the test metrics (None when there are none).

    Everything cheap is checked before the scene is loaded: the config (schema and schedule), ``--out``
    (a writable folder, empty for a new run), and on resume the run's lock, the keys a resume may change and
    ``--data`` against the run's scene. Overrides given on resume are recorded in the run's config.yaml.
    ``view`` = (host, port): serve the model in the web viewer while it trains (``retinexgs.view.live``)."""
    run_dir = Path(run_dir)
    device = pick_device(device)
    config_files, overrides = list(config_files), list(overrides)
    changes: Dict = {}
    relocating = False
    with contextlib.ExitStack() as stack:
        if resume:
            if not (run_dir / "config.yaml").is_file():
                raise UserError(f"--resume: {run_dir} is not a run folder (no config.yaml)")
            check_writable_folder(run_dir)
            stack.enter_context(run_lock(run_dir))
            recorded, recorded_scene = read_run_config(run_dir, log)
            cfg, changes = resume_config(recorded, config_files, overrides, run_dir, _checkpoint_step(run_dir))
            scene_path, relocating = resume_scene(recorded_scene, scene_path, relocate_scene, run_dir)
        else:
            if relocate_scene:
                raise UserError("--relocate-scene applies only with --resume (it points a run at its moved scene)")
            check_writable_folder(run_dir)
            if not is_empty_run_folder(run_dir):
                raise UserError(f"run folder {run_dir} already exists and is not empty; pass --resume to continue "
                                "it or choose another --out")
            cfg = load_config(config_files, overrides)
        scene = open_scene(Path(scene_path), cfg)
        log(scene.summary())
        if relocating:
            ckpt = latest_checkpoint(run_dir)
            names = load_checkpoint(ckpt).get("train_views") if ckpt is not None else None
            if not check_same_views(names, [v.name for v in scene.train], recorded_scene, Path(scene_path)):
                log(f"--relocate-scene: {run_dir} has no record of its training views to compare with (a "
                    "checkpoint from an older version); the new scene is taken as it is")
        log(build_schedule(cfg).describe())
        if device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        # The trainer reads every image and decomposition first: bad input fails before the run folder is made.
        trainer = Trainer(cfg, scene, run_dir, device, resume=resume, progress=progress, log=log)
        if not resume:
            run_dir.mkdir(parents=True, exist_ok=True)
            stack.enter_context(run_lock(run_dir))
            if not is_empty_run_folder(run_dir):  # another trainer made it while this one was loading
                raise UserError(f"run folder {run_dir} was filled by another trainer meanwhile; choose another --out")
        if not resume or changes or relocating:
            write_run_config(run_dir, cfg, scene_path)  # atomic: a later --resume continues with these settings
            for key, (old, new) in changes.items():
                log(f"--resume: {key} {old!r} -> {new!r} (recorded in {run_dir / 'config.yaml'})")
            if relocating:
                log(f"--relocate-scene: the run now reads its scene from {Path(scene_path).resolve()}")
        if view is not None:
            from retinexgs.view.live import start_live_viewer
            stack.callback(start_live_viewer(trainer, scene, view[0], view[1], log).stop)
        return _train_and_evaluate(trainer, cfg, scene, run_dir, device, log)


def _train_and_evaluate(trainer: Trainer, cfg: Dict, scene: Scene, run_dir: Path, device: str,
                        log: Callable[[str], None]) -> Optional[Dict]:
    stats: Dict = {"device": torch.cuda.get_device_name() if device.startswith("cuda") else "cpu"}
    if trainer.step >= cfg["steps"]:
        log(f"{run_dir} has already finished its {cfg['steps']} steps")
    else:
        values = trainer.train()
        values.setdefault("total_seconds", values["seconds"])
        stats.update(train_seconds=round(values["total_seconds"], 1), steps=cfg["steps"])
        if device.startswith("cuda"):
            stats["peak_gpu_memory_gb"] = round(torch.cuda.max_memory_allocated() / 2**30, 3)
        resumed = values["total_seconds"] - values["seconds"] > 0.5
        took = (f"{values['total_seconds']:.0f} s in all ({values['seconds']:.0f} s this session)" if resumed
                else f"{values['seconds']:.0f} s")
        log(f"trained {cfg['steps']} steps in {took}, {len(trainer.model.gaussians)} Gaussians"
            + (f", peak GPU memory {stats['peak_gpu_memory_gb']:.2f} GB" if "peak_gpu_memory_gb" in stats else ""))
    stats["gaussians"] = len(trainer.model.gaussians)
    return evaluate(render_function(trainer.model, cfg, trainer.active_degree(cfg["steps"])), scene, run_dir,
                    cfg["eval"]["lpips"], log, extra={"train": stats})


def render_function(model: RetinexGSModel, cfg: Dict, degree: int, exposure: Optional[float] = None,
                    gamma: Optional[float] = None, fast: bool = True,
                    renderer: Optional[InferenceRenderer] = None) -> Callable[[Union[View, Camera]], Dict]:
    """view (or a renderer camera) -> the model's output maps (``rgb``, and ``R``, ``L``, ``S_rec`` for RetinexGS);
    for the post-enhancement baseline, LR3M enhances the render.

    ``fast`` renders through an :class:`~retinexgs.model.inference.InferenceRenderer` (the fused colour kernel,
    CUDA graphs; same images as ``model.render``), built here once or passed as ``renderer`` (the viewer keeps
    one across frames); ``fast=False`` calls ``model.render``."""
    model.eval()
    if fast and renderer is None:
        renderer = InferenceRenderer(model, degree)

    def fn(view: Union[View, Camera]) -> Dict:
        camera = view if isinstance(view, Camera) else view_camera(view)
        with torch.no_grad():
            if fast:
                res = renderer.render(camera, exposure=exposure, gamma=gamma, degree=degree)
            else:
                res = model.render(camera, degree, exposure=exposure, gamma=gamma)
            if cfg["method"] == "post":
                from retinexgs.retinex import decompose, enhance_for_viewing
                method = cfg["decomposer"]["method"] if cfg["decomposer"]["method"] != "none" else "lr3m"
                R, L = decompose(res["rgb"].clamp(0, 1), method, **cfg["decomposer"]["params"])
                res = dict(res, rgb=enhance_for_viewing(R, L))
        return res

    return fn


def load_run(run_dir: Path, device: Optional[str] = None) -> Tuple[Dict, Scene, RetinexGSModel, int]:
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
    model = RetinexGSModel(GaussianModel.empty_like_state(gstate, cfg["model"]["sh_degree"]), cfg["model"],
                           cfg["method"] == "retinexgs")
    model.load_state_dict(state["model"])
    model.to(pick_device(device))
    scene = open_scene(scene_path, cfg)
    return cfg, scene, model, int(state["step"])


def eval_run(run_dir: Path, device: Optional[str] = None, log: Callable[[str], None] = print) -> Optional[Dict]:
    """Re-evaluate a saved run (rewrites metrics.json and renders/test)."""
    cfg, scene, model, step = load_run(run_dir, device)
    return evaluate(render_function(model, cfg, active_sh_degree(cfg, step)), scene, Path(run_dir),
                    cfg["eval"]["lpips"], log)
