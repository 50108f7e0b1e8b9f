"""Run folders: create, train, resume, reload and evaluate (what the train / eval / demo commands call)."""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable, Dict, Iterable, Optional

import torch

from retinexgs.data.photo_balance import describe_photo_balance
from retinexgs.data import Scene
from retinexgs.errors import UserError
from retinexgs.evaluate.evaluate import evaluate
from retinexgs.run.checkpoint import latest_checkpoint, load_checkpoint
from retinexgs.config.schema import Config
from retinexgs.run.config import load_config
from retinexgs.train.resume import check_same_views, check_writable_folder, is_empty_run_folder, resume_config, resume_scene, run_lock
from retinexgs.run.folder import read_run_config
from retinexgs.model.schedule import build_schedule
from retinexgs.retinex.cache import scene_cache_root
from retinexgs.train.trainer import Trainer
from retinexgs.run.folder import write_run_config
from retinexgs.run.folder import open_scene, pick_device
from retinexgs.run.render import render_function
from retinexgs.train.distributed import Distributed, gradient_params, init_from_env
from retinexgs.train.sfm_preview import scene_sfm_denoise


def _checkpoint_step(run_dir: Path) -> int:
    ckpt = latest_checkpoint(run_dir)
    return int(ckpt.stem.split("_")[-1]) if ckpt is not None else 0


def train_run(scene_path: Optional[Path], run_dir: Path, config_files: Iterable[str] = (),
              overrides: Iterable[str] = (), device: Optional[str] = None, resume: bool = False,
              progress: bool = True, log: Callable[[str], None] = print,
              relocate_scene: bool = False,
              on_trainer: Optional[Callable[[Trainer, Scene, Callable[[str], None]], Callable[[], None]]] = None
              ) -> Optional[Dict]:
    """Train (or resume) a run and evaluate it; returns the test metrics (None when there are none).

    Everything cheap is checked before the scene is loaded: the config (schema and schedule), ``--out``
    (a writable folder, empty for a new run), and on resume the run's lock, the keys a resume may change and
    ``--data`` against the run's scene. Overrides given on resume are recorded in the run's config.yaml.
    ``on_trainer(trainer, scene, log)``: called once the run is set up, before the first step; it returns a
    function called when training ends (``train --view`` serves the live model this way: ``retinexgs.viewer.live``).

    Launched by torchrun with several ranks (:mod:`retinexgs.train.distributed`), every rank runs this: the
    checks everywhere, then rank 0 reads the scene first (its caches) and the others after it, the
    decomposition in shards, rank 0 alone creates and locks the run folder and writes in it (the others are
    quiet), the evaluation in shards; the metrics are returned on every rank."""
    run_dir = Path(run_dir)
    device = pick_device(device)
    dist, device = init_from_env(device)
    ok = False
    try:
        result = _train_run(dist, scene_path, run_dir, config_files, overrides, device, resume,
                            progress and dist.is_main, log if dist.is_main else _quiet, relocate_scene,
                            on_trainer if dist.is_main else None)
        ok = True
        return result
    finally:
        dist.close(ok)


def _quiet(message: str) -> None:
    """The log of ranks other than 0."""


def _train_run(dist: Distributed, scene_path: Optional[Path], run_dir: Path, config_files: Iterable[str],
               overrides: Iterable[str], device: str, resume: bool, progress: bool, log: Callable[[str], None],
               relocate_scene: bool, on_trainer) -> Optional[Dict]:
    config_files, overrides = list(config_files), list(overrides)
    changes: Dict = {}
    relocating = False
    with contextlib.ExitStack() as stack:
        if resume:
            if not (run_dir / "config.yaml").is_file():
                raise UserError(f"--resume: {run_dir} is not a run folder (no config.yaml)")
            check_writable_folder(run_dir)
            if dist.is_main:
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
        # Every rank has checked --out before rank 0 creates anything in it.
        dist.barrier("every rank's checks of the run folder")
        # Rank 0 reads the scene first: it fills the scene's caches (undistorted or downscaled photos, SfM).
        # A bare folder's SfM denoises its previews by data.sfm_denoise (the rule of `retinexgs sfm --denoise`).
        sfm_denoise = scene_sfm_denoise(cfg.data.sfm_denoise, lambda m: log(f"[sfm] {m}"))
        if dist.is_main:
            scene = open_scene(Path(scene_path), cfg, sfm_denoise=sfm_denoise)
        dist.barrier("rank 0's reading of the scene")
        if dist.enabled:  # ranks hand each other the decomposition's shards and the view store through the caches
            cache = dist.broadcast_object(str(scene_cache_root(scene.root, cfg.data.cache_dir)) if dist.is_main
                                          else None, "the scene's cache folder")
            dist.check_shared_folder(Path(cache), "the scene's cache folder")
        if not dist.is_main:
            scene = open_scene(Path(scene_path), cfg, sfm_denoise=sfm_denoise)
        log(scene.summary())
        if scene.train and scene.train[0].balance is not None:
            log(describe_photo_balance(scene.train[0].balance))
        if relocating:
            ckpt = latest_checkpoint(run_dir)
            names = load_checkpoint(ckpt)["train_views"] if ckpt is not None else None
            if not check_same_views(names, [v.name for v in scene.train], recorded_scene, Path(scene_path)):
                log(f"--relocate-scene: {run_dir} has no record of its training views to compare with (a "
                    "checkpoint from an older version); the new scene is taken as it is")
        log(build_schedule(cfg).describe())
        if device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        if dist.enabled:
            log(f"{dist.world} ranks ({dist.backend}), {dist.world * cfg.train.views_per_rank} views a step")
        dist.decompose_shard(scene, cfg, device, progress)
        # The trainer reads every image and decomposition first: bad input fails before the run folder is made.
        trainer = Trainer(cfg, scene, run_dir, device, resume=resume, progress=progress, log=log, dist=dist)
        if not resume and dist.is_main:
            run_dir.mkdir(parents=True, exist_ok=True)
            stack.enter_context(run_lock(run_dir))
            if not is_empty_run_folder(run_dir):  # another trainer made it while this one was loading
                raise UserError(f"run folder {run_dir} was filled by another trainer meanwhile; choose another --out")
        dist.barrier("rank 0's creation of the run folder")
        dist.check_shared_folder(run_dir, "the run folder")  # every rank resumes from its checkpoints
        if (not resume or changes or relocating) and dist.is_main:
            write_run_config(run_dir, cfg, scene_path)  # atomic: a later --resume continues with these settings
            for key, (old, new) in changes.items():
                log(f"--resume: {key} {old!r} -> {new!r} (recorded in {run_dir / 'config.yaml'})")
            if relocating:
                log(f"--relocate-scene: the run now reads its scene from {Path(scene_path).resolve()}")
        if on_trainer is not None:
            stack.callback(on_trainer(trainer, scene, log))
        return _train_and_evaluate(trainer, cfg, scene, run_dir, device, log, dist)


def _train_and_evaluate(trainer: Trainer, cfg: Config, scene: Scene, run_dir: Path, device: str,
                        log: Callable[[str], None], dist: Optional[Distributed] = None) -> Optional[Dict]:
    dist = dist if dist is not None else Distributed()
    stats: Dict = {"device": torch.cuda.get_device_name() if device.startswith("cuda") else "cpu"}
    if trainer.step >= cfg.steps:
        log(f"{run_dir} has already finished its {cfg.steps} steps")
    else:
        values = trainer.train()
        values.setdefault("total_seconds", values["seconds"])
        stats.update(train_seconds=round(values["total_seconds"], 1), steps=cfg.steps)
        if device.startswith("cuda"):
            stats["peak_gpu_memory_gb"] = round(torch.cuda.max_memory_allocated() / 2**30, 3)
            # what the caching allocator held at its peak: what a smaller card must have (issue 65's 24 GB goal)
            stats["peak_gpu_memory_reserved_gb"] = round(torch.cuda.max_memory_reserved() / 2**30, 3)
        # the views' set-up of this session (photos, priors, view store): most of time_to_first_step on a big capture
        stats["views_set_up_seconds"] = round(trainer.views_set_up_seconds, 1)
        # The large-scene benchmark's figures (ranks 1 for a plain run), gathered from every rank.
        stats.update(dist.training_stats(trainer.batch_size, trainer.session_views, values["seconds"],
                                         trainer.time_to_first_step, gradient_params(trainer.optimizer),
                                         {"first_step_seconds": trainer.first_step_seconds,
                                          "event_seconds": trainer.event_seconds,
                                          "event_steps": trainer.event_steps}))
        resumed = values["total_seconds"] - values["seconds"] > 0.5
        took = (f"{values['total_seconds']:.0f} s in all ({values['seconds']:.0f} s this session)" if resumed
                else f"{values['seconds']:.0f} s")
        log(f"trained {cfg.steps} steps in {took}, {len(trainer.model.gaussians)} Gaussians"
            + (f", peak GPU memory {stats['peak_gpu_memory_gb']:.2f} GB" if "peak_gpu_memory_gb" in stats else ""))
    stats["gaussians"] = len(trainer.model.gaussians)
    return evaluate(render_function(trainer.model, cfg, trainer.active_degree(cfg.steps), linear=True), scene, run_dir,
                    cfg.eval.lpips, log, extra={"train": stats}, shard=(dist.rank, dist.world),
                    sheet_max_side=cfg.eval.sheet_max_side,
                    gather=(lambda rows: dist.gather_objects(rows, "the evaluation's rows")) if dist.enabled else None)


