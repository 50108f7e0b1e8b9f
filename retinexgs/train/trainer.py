"""The RetinexGS training loop (and the plain-3DGS baselines): priors, model, optimiser, schedule, density
control, logging, atomic checkpoints and resume, and the final evaluation."""
from __future__ import annotations

import contextlib
import json
import math
import random
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import torch
from torch import Tensor
from torch.profiler import record_function

from retinexgs.data import Scene
from retinexgs.errors import UserError
from retinexgs.fileio import is_out_of_space, out_of_space_error
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.model.schedule import build_schedule
from retinexgs.render.pair_budget import PairBudget
from retinexgs.run.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from retinexgs.config.schema import Config
from retinexgs.strategy import build_strategy
from retinexgs.train.capture_setup import set_up_noise
from retinexgs.train.distributed import (Distributed, adam_betas_for_batch, gradient_params, lr_batch_factor,
                                         process_start_time, take_gradients)
from retinexgs.train.adam import adam_for
from retinexgs.train.divergence import DivergenceWatch, TrainingDiverged  # noqa: F401 (re-exported)
from retinexgs.train.graphs import ChannelGraphs, LossGraphs
from retinexgs.train.objective import build_objective, enhancement_objective  # noqa: F401 (re-exported)
from retinexgs.train.stop import DeferredStop
from retinexgs.train.view_setup import near_plane, prepare_views, scene_extent, view_statistics
from retinexgs.train.redenoise import Redenoise
from retinexgs.train.resolution import ResolutionSchedule
from retinexgs.train.views import TrainView, preload_bytes_per_pixel


def open_tensorboard(cfg: Config, run: Path, log: Callable[[str], None]):
    """A TensorBoard writer in ``RUN/tb`` where ``log.tensorboard`` asks for one and it is installed, else None."""
    if not cfg.log.tensorboard:
        return None
    try:
        from torch.utils.tensorboard import SummaryWriter
    except Exception:  # tensorboard not installed: the JSONL log still has everything
        log("tensorboard is not installed: losses are logged to train_log.jsonl only (pip install tensorboard)")
        return None
    return SummaryWriter(str(run / "tb"))


def _append_record(f, record: Dict) -> None:
    """Append one JSON line to the unbuffered ``train_log.jsonl`` (whole lines: a killed run leaves no cut
    line); a full disk raises a UserError naming the file."""
    data = (json.dumps(record) + "\n").encode("utf-8")
    try:
        while data:
            data = data[f.write(data):]
    except OSError as exc:
        if is_out_of_space(exc, Path(f.name).parent):
            raise out_of_space_error(f.name) from None
        raise


class Trainer:
    """Trains one run folder. ``resume`` continues from its newest checkpoint."""

    def __init__(self, cfg: Config, scene: Scene, run_dir: Path, device: str = "cpu", resume: bool = False,
                 progress: bool = True, log: Callable[[str], None] = print, emulate_graphs: bool = False,
                 dist: Optional[Distributed] = None) -> None:
        """``emulate_graphs``: on the CPU, run the CUDA-graph path of the step (the image losses' forward and
        backward apart, the gradients fed back) eagerly, for tests and op counts (:mod:`retinexgs.train.graphs`).
        ``dist``: this rank among several (:mod:`retinexgs.train.distributed`); None: the plain run."""
        self.cfg, self.scene, self.run = cfg, scene, Path(run_dir)
        self.device, self.progress, self.log = torch.device(device), progress, log
        self.seconds_before: float = 0.0  # training time recorded by the checkpoint resumed from
        self._session_start: Optional[float] = None  # set while train() runs
        if not scene.train:
            raise UserError(f"scene {scene.root} has no training views")
        self.method = cfg.method
        self.schedule = build_schedule(cfg)
        # train.resolution: coarse views early, for views above train.resolution_min_pixels
        self.resolution = ResolutionSchedule.from_config(cfg, [(v.width, v.height) for v in scene.train])
        log(self.resolution.describe())
        self.decomposed = self.method == "retinexgs"
        # The depth prior is RetinexGS's (the 3DGS baselines stay as published).
        self.depth_prior = self.decomposed and cfg.loss.w_depth > 0
        torch.manual_seed(cfg.seed)
        random.seed(cfg.seed)
        self._setup_dist = dist
        self.order: List[int] = []  # the rest of this epoch's view order (saved, so resume continues it)
        t_views = time.time()
        self.views, self.streamed, self._stats = prepare_views(cfg, scene, self.device, self.depth_prior, dist,
                                                               progress, log, self._upcoming_views)
        # the views' set-up (photos read, priors decomposed or loaded, a view store written): metrics.json's figure
        self.views_set_up_seconds = time.time() - t_views
        if self.streamed:  # a coarse stage keeps its pooled views where they fit the budget the full-size ones did not
            priors = self.method in ("retinexgs", "pre") and cfg.decomposer.method != "none"
            self.resolution.plan_streamed(preload_bytes_per_pixel(self.method, priors, self.depth_prior),
                                          cfg.train.views_on_device_gb)
        self.redenoise = Redenoise.for_run(cfg, scene, self.streamed, str(self.device))  # decomposer.redenoise_at
        self.extent = scene_extent(scene)
        self.step = 0
        state = None
        if resume:
            ckpt = latest_checkpoint(self.run)
            if ckpt is None:  # stopped before its first checkpoint (e.g. killed while decomposing)
                self.log(f"{self.run} has no checkpoint yet: starting from step 0")
            else:
                state = load_checkpoint(ckpt)
                self.log(f"resuming from {ckpt} (step {state['step']})")
        self._build(state, emulate_graphs)
        self._setup_batch(dist)

    # ---- set-up ----------------------------------------------------------------------------------------
    def _build(self, state: Optional[Dict], emulate_graphs: bool = False) -> None:
        mcfg = self.cfg.model
        if state is None:
            pts, cols = self.scene.points, self.scene.colors
            if pts.shape[0] > mcfg.max_init_points:
                idx = torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(self.cfg.seed))
                pts, cols = pts[idx[: mcfg.max_init_points]], cols[idx[: mcfg.max_init_points]]
            gaussians = GaussianModel.from_points(pts, cols, mcfg.sh_degree, mcfg.init_opacity,
                                                  brighten=self.decomposed)
        else:
            gstate = {k[len("gaussians."):]: v for k, v in state["model"].items() if k.startswith("gaussians.")}
            gaussians = GaussianModel.empty_like_state(gstate, mcfg.sh_degree)
        self.model = RetinexGSModel(gaussians, mcfg, self.decomposed, self.scene.capture).to(self.device)
        if state is None:
            self.model.initialise_levels(lambda: view_statistics(self.cfg, self.views, self._stats),
                                         lambda: near_plane(self.cfg, self.scene, self.log))
        self.noise = set_up_noise(self.cfg, self.scene, self.model, state, self.device, self._setup_dist, self.log)
        groups = self.model.param_groups(self.cfg.lr, self.extent)
        rates = {group["name"]: group["lr"] for group in groups}
        # One Adam kernel for every group on the GPU (train/adam.py: torch's fused Adam launches once per group).
        self.optimizer = adam_for(self.device, groups, eps=1e-15)
        self.strategy = build_strategy(self.cfg.density, self.extent, self.schedule, self.cfg.seed)
        self.objective = build_objective(self.cfg, self.model, self.schedule, self.strategy, self.noise,
                                         self.scene.views_per_point, self.log)
        if state is not None:
            self.model.load_state_dict(state["model"])
            self.optimizer.load_state_dict(state["optimizer"])
            for group in self.optimizer.param_groups:  # the config's rates: a resume may change them
                group["lr"] = rates[group["name"]]
            self.step = int(state["step"])
            # Training time of the steps the checkpoint holds (0 for a format-0 checkpoint: its migration).
            self.seconds_before = float(state["train_seconds"])
            torch.set_rng_state(state["rng"])
            random.setstate(state["py_rng"])
            self.order = list(state["order"])
            self.strategy.load_state_dict(state["density"], self.device)
        self.divergence = DivergenceWatch(self.model, self.run, self.step)
        self.pairs = PairBudget(self.cfg.train.pair_margin)  # train.pair_margin: binning without a host sync
        # The image losses as CUDA graphs (train.cuda_graphs; CUDA only, eager elsewhere).
        self.graphs: Optional[LossGraphs] = None
        self.channel_graphs: Optional[ChannelGraphs] = None
        self._graph_failures_logged: set = set()
        if self.cfg.train.cuda_graphs and (self.device.type == "cuda" or emulate_graphs):
            self.graphs = LossGraphs(self.objective.graphed_loss, self.objective.graphed_params(),
                                     emulate=emulate_graphs)
            self.channel_graphs = ChannelGraphs(self.model, emulate=emulate_graphs)

    # ---- one step ----------------------------------------------------------------------------------------
    def _means_lr(self, step: int) -> float:
        lr = self.cfg.lr
        t = min(step / max(self.cfg.steps, 1), 1.0)
        return self.extent * math.exp((1 - t) * math.log(lr.means) + t * math.log(lr.means_final))

    def active_degree(self, step: int) -> int:
        return self.schedule.sh_degree_at(step)

    def _log_graph_failures(self, failures: Dict) -> None:
        for key, why in failures.items():
            if key not in self._graph_failures_logged:
                self._graph_failures_logged.add(key)
                self.log(f"CUDA graph capture failed for {key[0]} images ({why}); that size trains eagerly")

    def render_view(self, tv: TrainView, step: int, graphed: bool = True) -> Dict[str, Tensor]:
        """The step's render of ``tv`` (no EnhancementNet: it runs inside the loss, where its losses need it);
        ``graphed``: the per-Gaussian channels through their CUDA graphs when the trainer has them."""
        with record_function("step/render"):
            colors = None
            if graphed and self.channel_graphs is not None:
                colors = self.channel_graphs.run(self.active_degree(step), tv.center,
                                                 self.schedule.steps_unchanged(step))
                for key, why in self.channel_graphs.failures.items():
                    if key not in self._graph_failures_logged:
                        self._graph_failures_logged.add(key)
                        self.log(f"CUDA graph capture of the Gaussians' channels failed ({why}); they run eagerly "
                                 "until the Gaussians change")
            return self.model.render(tv.camera, self.active_degree(step), validate=False, enhance=False,
                                     center=tv.center, colors=colors, depth=self.depth_prior,
                                     near=self.cfg.model.near_in_training, pairs=self.pairs,
                                     packed=self.depth_prior and self.graphs is not None)

    def train_step(self, step: int, tv, check: bool = True) -> Dict[str, float]:
        """One optimisation step on view ``tv`` (or on this rank's list of the step's views: each is rendered
        and back-propagated in turn, the gradients summed). With ``check`` (and always before densification or
        an opacity reset) the loss terms and parameters of every step since the last check are checked for
        NaN/inf (:class:`TrainingDiverged`) and this step's loss values (the mean over the step's views) are
        returned; otherwise nothing is read back from the device (the step never waits for the GPU; binning's pair
        count is read a step late, ``train.pair_margin``) and the result holds only a density event, if any. A batch of B > 1 views
        (``batch_size``: ranks × ``train.views_per_rank``) steps on the mean gradient over the B views: one
        all-reduce of the gradients across the ranks after the backward, before the optimiser step; the
        density statistics are summed over the ranks before a densification, and rank 0's Gaussians broadcast
        after any density event (:mod:`retinexgs.train.distributed`)."""
        views = list(tv) if isinstance(tv, (list, tuple)) else [tv]
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = self._means_lr(step) * self.lr_scale
        several = len(views) > 1
        acc, per_view = None, []
        for view in views:
            res = self.render_view(view, step)
            terms = (self.objective.backward_graphed(self.graphs, res, view, step, self._log_graph_failures)
                     if self.graphs is not None else None)
            if terms is None:
                with record_function("step/loss"):
                    terms = self.objective.loss(res, view, step)
                with record_function("step/backward"):
                    terms["total"].backward()
            if several:  # this view's gradients go into the step's sum (p.grad free for the next view)
                per_view.append({k: v.detach() for k, v in terms.items()})
                acc = take_gradients(gradient_params(self.optimizer), acc)
            else:
                with record_function("step/watch"):
                    self.divergence.watch(terms, step)
            with record_function("step/density"):
                self.strategy.after_backward(res["out"], view.camera.width, view.camera.height)
            del res
        if several:
            for p, g in zip(gradient_params(self.optimizer), acc):
                p.grad = g
            with record_function("step/watch"):
                self.divergence.watch({k: sum(t[k] for t in per_view) / len(per_view) for k in per_view[0]}, step)
        if self.batch_size > 1:
            with record_function("step/all_reduce"):
                self.dist.reduce_gradients(gradient_params(self.optimizer), self.batch_size, step, verify=check)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.strategy.after_optimizer_step(self.model.gaussians, self.optimizer, step)
        values: Dict[str, float] = {}
        if check or self.strategy.edits_at(step):
            with record_function("step/check"):
                values = self.dist.mean_values(self.check_finite(step), step)
        size = max(max(v.camera.width, v.camera.height) for v in views)
        if self.dist.enabled and self.strategy.will_edit(step):
            size = self.dist.reduce_strategy(self.strategy, len(self.model.gaussians), size, step)
        event = self.strategy.step(step, self.model.gaussians, self.optimizer, size)
        if event:
            values["event"] = event  # type: ignore[assignment]
            self.pairs.reset()  # relocated or reset Gaussians (N may be unchanged): the next binning re-measures
            if self.dist.enabled:
                values["ranks_agree"] = self.dist.sync_gaussians(self.model.gaussians, self.optimizer, step)
        return values

    # ---- divergence (retinexgs/train/divergence.py) -------------------------------------------------------
    def check_finite(self, step: int) -> Dict[str, float]:
        """Raise :class:`TrainingDiverged` naming the first loss term or parameter that became non-finite since the
        last check (:meth:`DivergenceWatch.check`); returns the last step's loss values."""
        return self.divergence.check(step)

    # ---- the loop ----------------------------------------------------------------------------------------
    def _setup_batch(self, dist: Optional[Distributed]) -> None:
        """A step's batch: ``batch_size`` = ranks × ``train.views_per_rank`` views; every learning rate scaled
        by ``train.lr_batch_scaling`` of it (1 for a batch of one view), Adam's betas by
        ``train.momentum_batch_scaling``. With several ranks, rank 0's model
        state (parameters and buffers: ``illum_ref``, the mean background) is broadcast to the others."""
        self.dist = dist if dist is not None else Distributed(device=self.device)
        tcfg = self.cfg.train
        self.batch_size = self.dist.world * tcfg.views_per_rank
        self.lr_scale = lr_batch_factor(tcfg.lr_batch_scaling, self.batch_size)
        # Set on every start, a resume included: a checkpoint holds the betas of the batch it was written with.
        betas = adam_betas_for_batch(tcfg.momentum_batch_scaling, self.batch_size)
        for group in self.optimizer.param_groups:
            group["lr"] *= self.lr_scale
            group["betas"] = betas
        self.time_to_first_step: Optional[float] = None  # seconds from the process's start to step 1's end
        self.first_step_seconds: Optional[float] = None  # the last session's first step; train() sets these
        self.event_seconds, self.event_steps = 0.0, 0
        self.session_views = 0  # views trained on in the last train() call, over every rank
        if self.dist.enabled:
            self.dist.broadcast_(list(self.model.state_dict().values()), "the model's initial state")

    def _upcoming_views(self) -> List[int]:
        """This rank's views of the next two steps, nearest first, as far as the current order holds them (what
        the streamed views prefetch): entries r and r + B from the order's end, for rank r of a batch of B."""
        r, b = self.dist.rank, self.batch_size
        return [self.order[-1 - r - k * b] for k in range(2) if r + k * b < len(self.order)]

    def _batch_indices(self) -> List[int]:
        """This rank's views of the next step: the next ``batch_size`` entries of the shared view order (a new
        shuffle of every view, the same on every rank, each time it runs out), entries r, r + N, ... for rank
        r of N. One rank taking B views and N ranks taking B / N each see the same views in each step."""
        batch = []
        for _ in range(self.batch_size):
            if not self.order:
                self.order = list(range(len(self.views)))
                random.shuffle(self.order)
                if self.dist.enabled:  # seeded alike on every rank; rank 0's, should anything have drawn apart
                    self.order = self.dist.broadcast_object(self.order, "the view order")
            batch.append(self.order.pop())
        return batch[self.dist.rank::self.dist.world]

    def checkpoint_state(self) -> Dict:
        # The config as plain data (not the typed object): old and new code load the checkpoint alike.
        return {"step": self.step, "config": self.cfg.model_dump(), "model": self.model.state_dict(),
                "optimizer": self.optimizer.state_dict(), "rng": torch.get_rng_state(),
                "py_rng": random.getstate(), "order": list(self.order), "density": self.strategy.state_dict(), "normalization": {
                    "center": self.scene.normalization.center, "scale": self.scene.normalization.scale},
                "scene_root": str(self.scene.root), "train_views": [v.name for v in self.scene.train],
                "train_seconds": self.train_seconds(),
                **self.noise.state_dict(),
                # For information (a checkpoint resumes with any number of ranks): how it was trained.
                "ranks": self.dist.world, "views_per_step": self.batch_size}

    def train_seconds(self) -> float:
        """Seconds spent training the steps so far, over every session of the run (a resumed run adds its
        time to what its checkpoint recorded; the steps lost to a kill since the last checkpoint do not count)."""
        return self.seconds_before + (time.time() - self._session_start if self._session_start else 0.0)

    def save(self) -> Optional[Path]:
        """Write a checkpoint of the current step (after checking every step since the last check); only rank 0
        writes (None on the others: the ranks' parameters are identical)."""
        if self.divergence.checked_through < self.step:
            self.check_finite(self.step)
        if not self.dist.is_main:
            return None
        return save_checkpoint(self.run, self.step, self.checkpoint_state(), self.cfg.checkpoint.keep)

    def _save_on_stop(self, stop: DeferredStop) -> None:
        """Write a checkpoint of the last whole step (unless one exists), say where, and raise as the signal
        would have: ``--resume`` continues from exactly here."""
        done = latest_checkpoint(self.run)
        if self.step > 0 and (done is None or not done.name.endswith(f"_{self.step:06d}.pt")):
            path = self.save()
            if path is not None:
                self.log(f"stopped at step {self.step}: checkpoint {path} written; "
                         f"retinexgs train --out {self.run} --resume continues from it")
        elif self.step > 0 and self.dist.is_main:
            self.log(f"stopped at step {self.step}, checkpointed in {done}; "
                     f"retinexgs train --out {self.run} --resume continues from it")
        stop.raise_now()

    def train(self, stop_after: Optional[int] = None) -> Dict[str, float]:
        """Train up to ``cfg.steps`` (or ``stop_after`` more steps); returns the last step's loss values."""
        from tqdm import tqdm

        total_steps = self.cfg.steps
        end = total_steps if stop_after is None else min(total_steps, self.step + stop_after)
        main = self.dist.is_main  # only rank 0 logs, shows progress and writes
        writer = open_tensorboard(self.cfg, self.run, self.log) if main else None
        log_path = self.run / "train_log.jsonl"
        values: Dict[str, float] = {}
        t0 = self._session_start = time.time()
        first = self.step + 1
        if self.redenoise is not None and self.redenoise.due(self.step, resumed_from=first):
            self._redenoise()  # a resumed run read its views fresh: their priors as the run had them then
        # What the steady step rate excludes (the scale benchmark's figures): the session's first step (warm-up,
        # graph captures) and each density event with the step after it (its re-captures), timed between syncs.
        self.first_step_seconds, self.event_seconds, self.event_steps = None, 0.0, 0
        timed_from: Optional[Tuple[float, int]] = None
        timed_through = 0
        bar = tqdm(total=end, initial=self.step, disable=not self.progress or not main, desc="train",
                   dynamic_ncols=True)
        # unbuffered: a record is on disk when written
        with open(log_path, "ab", buffering=0) if main else contextlib.nullcontext() as log_file, \
                DeferredStop() as stop:
            while self.step < end:
                indices = self._batch_indices()
                self.step += 1
                self.dist.test_fault(self.step)
                check = (self.step % self.cfg.log.every == 0 or self.step == end
                         or self.step % self.cfg.checkpoint.every == 0)
                views = [self.resolution.view_at((lambda i=i: self.views[i]) if self.streamed else self.views[i], i,
                                                 self.step, cache=not self.streamed) for i in indices]
                if self.step > first and self.strategy.edits_at(self.step):
                    if timed_from is None:
                        self._sync()
                        timed_from = (time.time(), self.step)
                    timed_through = self.step + 1
                values = self.train_step(self.step, views[0] if len(views) == 1 else views, check=check)
                if self.step == first:
                    self._sync()
                    self.time_to_first_step = time.time() - process_start_time()
                    self.first_step_seconds = time.time() - t0
                if timed_from is not None and self.step >= min(timed_through, end):
                    self._sync()
                    self.event_seconds += time.time() - timed_from[0]
                    self.event_steps += self.step - timed_from[1] + 1
                    timed_from = None
                if self.redenoise is not None and self.redenoise.due(self.step):
                    self._redenoise()
                event = values.pop("event", None)
                agree = values.pop("ranks_agree", None)
                if event and log_file is not None:
                    _append_record(log_file, {"step": self.step, "event": event,
                                              "gaussians": len(self.model.gaussians)}
                                   | ({} if agree is None else {"ranks_agree": agree}))
                if log_file is not None and (self.step % self.cfg.log.every == 0 or self.step == end):
                    n = len(self.model.gaussians)
                    bar.set_postfix({k: f"{v:.4f}" for k, v in values.items() if k in
                                     ("total", "sup_rec", "sup_r", "sup_l", "exp", "rgb")} | {"N": n})
                    _append_record(log_file, {"step": self.step, "gaussians": n, "seconds": self.train_seconds(),
                                               **values})
                    if writer:
                        for k, v in values.items():
                            writer.add_scalar(f"loss/{k}", v, self.step)
                        writer.add_scalar("gaussians", n, self.step)
                if self.step % self.cfg.checkpoint.every == 0 or self.step == end:
                    self.save()
                bar.update(1)
                if stop.requested:  # Ctrl-C / SIGTERM noted during this step: save it, then stop
                    bar.close()
                    self._save_on_stop(stop)
        bar.close()
        if writer:
            writer.close()
        if main and (dropped := self.pairs.summary()):  # renders whose sync-free binning overflowed
            self.log(dropped)
        values["seconds"] = time.time() - t0
        self.session_views = (self.step - first + 1) * self.batch_size  # this session's views, all ranks
        values["total_seconds"] = self.train_seconds()
        self.seconds_before, self._session_start = values["total_seconds"], None
        return values

    def _redenoise(self) -> None:
        """The views' priors made again from the views re-denoised with the model's render as the pilot."""
        degree = self.active_degree(self.step)
        self.redenoise.run(self.views, lambda tv, depth: self.model.render(
            tv.camera, degree, validate=False, enhance=False, center=tv.center, depth=depth), self.cfg)
        self.resolution.forget_views()  # pooled copies hold the old priors

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
