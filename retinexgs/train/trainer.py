"""The RetinexGS training loop (and the plain-3DGS baselines): priors, model, optimiser, schedule, density
control, logging, atomic checkpoints and resume, and the final evaluation."""
from __future__ import annotations

import json
import math
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional

import torch
import yaml
from torch import Tensor

from retinexgs.data import Scene, View
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write_text
from retinexgs.model.density import DensityController
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.render import Camera
from retinexgs.train import losses
from retinexgs.train.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from retinexgs.train.schedule import build_schedule


class TrainingDiverged(UserError):
    """A loss term or parameter became non-finite; the last good checkpoint is left intact."""


def active_sh_degree(cfg: Dict, step: int) -> int:
    """The SH degree the model renders with after ``step`` steps (it grows by one every sh_degree_every)."""
    return build_schedule(cfg).sh_degree_at(step)


def view_camera(view: View) -> Camera:
    """The renderer's camera for a data-layer view."""
    return Camera(view.world_to_camera(), view.fx, view.fy, view.cx, view.cy, view.width, view.height)


def scene_extent(scene: Scene) -> float:
    """1.1 x the largest distance of a train camera from the centroid of the train cameras (3DGS)."""
    centers = torch.stack([v.camera_center for v in scene.train]).float()
    return float(1.1 * (centers - centers.mean(0)).norm(dim=-1).max().clamp_min(1e-3))


def to_bchw(x: Tensor) -> Tensor:
    return x.permute(2, 0, 1).unsqueeze(0)


@dataclass
class TrainView:
    """A training view on the device: camera, low-light image S and its 2D priors / baseline target."""

    camera: Camera
    S: Tensor                   # [H,W,3]
    R: Optional[Tensor] = None  # [H,W,3]
    L: Optional[Tensor] = None  # [H,W,1]
    target: Optional[Tensor] = None  # [H,W,3], baselines


def decompose_views(views: List[View], cfg: Dict, device: str, progress: bool, scene_root: Path) -> List:
    """(R, L) per view from the per-scene cache (computed where missing; ``retinexgs decompose`` fills the
    same cache, see :func:`retinexgs.retinex.cache.scene_cache_root`)."""
    from retinexgs.retinex.cache import load_or_compute, scene_cache_root

    dcfg = cfg["decomposer"]
    return load_or_compute([v.image_path for v in views], dcfg["method"], dict(dcfg["params"]) or None,
                           cache_dir=scene_cache_root(scene_root, cfg["data"]["cache_dir"]),
                           device=dcfg["device"] or device, progress=progress,
                           cache_hint="--set data.cache_dir=DIR")


class Trainer:
    """Trains one run folder. ``resume`` continues from its newest checkpoint."""

    def __init__(self, cfg: Dict, scene: Scene, run_dir: Path, device: str = "cpu", resume: bool = False,
                 progress: bool = True, log: Callable[[str], None] = print) -> None:
        self.cfg, self.scene, self.run = cfg, scene, Path(run_dir)
        self.device, self.progress, self.log = torch.device(device), progress, log
        if not scene.train:
            raise UserError(f"scene {scene.root} has no training views")
        self.method = cfg["method"]
        self.schedule = build_schedule(cfg)
        self.decomposed = self.method == "retinexgs"
        torch.manual_seed(cfg["seed"])
        random.seed(cfg["seed"])
        self.views = self._prepare_views()
        self.extent = scene_extent(scene)
        self.step = 0
        self.order: List[int] = []  # the rest of this epoch's view order (saved, so resume continues it)
        state = None
        if resume:
            ckpt = latest_checkpoint(self.run)
            if ckpt is None:  # stopped before its first checkpoint (e.g. killed while decomposing)
                self.log(f"{self.run} has no checkpoint yet: starting from step 0")
            else:
                state = load_checkpoint(ckpt)
                self.log(f"resuming from {ckpt} (step {state['step']})")
        self._build(state)

    # ---- set-up ----------------------------------------------------------------------------------------
    def _prepare_views(self) -> List[TrainView]:
        cfg, dev = self.cfg, self.device
        views = [TrainView(view_camera(v), v.image.to(dev)) for v in self.scene.train]
        needs_priors = self.method in ("retinexgs", "pre") and cfg["decomposer"]["method"] != "none"
        if self.method == "pre" and cfg["decomposer"]["method"] == "none":
            raise UserError("the pre-enhancement baseline needs a decomposer (decomposer.method lr3m or lime)")
        if needs_priors:
            self.log(f"2D priors: {cfg['decomposer']['method']} on {len(views)} views (cached per scene)")
            priors = decompose_views(self.scene.train, cfg, str(dev), self.progress, self.scene.root)
            for tv, (R, L) in zip(views, priors):
                if R.shape[:2] != tv.S.shape[:2]:
                    raise UserError(f"cached decomposition has size {tuple(R.shape[:2])} but the view is "
                                    f"{tuple(tv.S.shape[:2])}; delete the retinex cache")
                tv.R, tv.L = R.to(dev), L.to(dev)
                if self.method == "pre":
                    from retinexgs.retinex import enhance_for_viewing
                    tv.target = enhance_for_viewing(tv.R, tv.L)
        for tv in views:
            if tv.target is None:
                tv.target = tv.S
        return views

    def _build(self, state: Optional[Dict]) -> None:
        mcfg = self.cfg["model"]
        if state is None:
            pts, cols = self.scene.points, self.scene.colors
            if pts.shape[0] > mcfg["max_init_points"]:
                idx = torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(self.cfg["seed"]))
                pts, cols = pts[idx[: mcfg["max_init_points"]]], cols[idx[: mcfg["max_init_points"]]]
            gaussians = GaussianModel.from_points(pts, cols, mcfg["sh_degree"], mcfg["init_opacity"],
                                                  brighten=self.decomposed)
        else:
            gstate = {k[len("gaussians."):]: v for k, v in state["model"].items() if k.startswith("gaussians.")}
            gaussians = GaussianModel.empty_like_state(gstate, mcfg["sh_degree"])
        self.model = RetinexGSModel(gaussians, mcfg, self.decomposed).to(self.device)
        if self.decomposed and state is None:
            self.model.illum_ref.fill_(self.illumination_reference())
        lr = self.cfg["lr"]
        g = self.model.gaussians
        groups = [
            {"params": [g.means], "lr": lr["means"] * self.extent, "name": "means"},
            {"params": [g.quats], "lr": lr["quats"], "name": "quats"},
            {"params": [g.log_scales], "lr": lr["scales"], "name": "log_scales"},
            {"params": [g.opacity_logits], "lr": lr["opacities"], "name": "opacity_logits"},
            {"params": [g.sh_dc], "lr": lr["sh_dc"], "name": "sh_dc"},
            {"params": [g.sh_rest], "lr": lr["sh_rest"], "name": "sh_rest"},
        ]
        if self.decomposed:
            groups += [{"params": list(self.model.illumination.parameters()), "lr": lr["illumination"],
                        "name": "illumination"},
                       {"params": list(self.model.enhancement.parameters()), "lr": lr["enhancement"],
                        "name": "enhancement"}]
        rates = {group["name"]: group["lr"] for group in groups}
        # Fused Adam on the GPU: one kernel per parameter group instead of a dozen (the step is launch-bound).
        self.optimizer = torch.optim.Adam(groups, eps=1e-15, fused=self.device.type == "cuda")
        self.density = DensityController(self.cfg["density"], self.extent, self.schedule)
        if state is not None:
            self.model.load_state_dict(state["model"])
            self.optimizer.load_state_dict(state["optimizer"])
            for group in self.optimizer.param_groups:  # the config's rates: a resume may change them
                group["lr"] = rates[group["name"]]
            self.step = int(state["step"])
            torch.set_rng_state(state["rng"])
            random.setstate(state["py_rng"])
            self.order = list(state.get("order", []))
            self.density.load_state_dict(state.get("density", {}), self.device)

    def illumination_reference(self) -> float:
        """L_ref, the scene's "full light" level that the enhancement normalises L̂ by: the median over the
        training views of the ``model.enhancement.ref_quantile`` quantile of the 2D prior L (of max-RGB of S
        without priors, the usual initial illumination estimate). 1 when the quantile is null (no
        normalisation: L_enh = L̂^g as the paper writes it)."""
        q = self.cfg["model"]["enhancement"]["ref_quantile"]
        if q is None:
            return 1.0
        per_view = []
        for tv in self.views:
            L = tv.L if tv.L is not None else tv.S.amax(dim=-1)
            flat = L.reshape(-1).float()
            per_view.append(flat.kthvalue(min(flat.numel(), max(1, round(float(q) * flat.numel())))).values)
        return float(torch.stack(per_view).median().clamp_min(1e-3))

    # ---- one step ----------------------------------------------------------------------------------------
    def _means_lr(self, step: int) -> float:
        lr = self.cfg["lr"]
        t = min(step / max(self.cfg["steps"], 1), 1.0)
        return self.extent * math.exp((1 - t) * math.log(lr["means"]) + t * math.log(lr["means_final"]))

    def active_degree(self, step: int) -> int:
        return self.schedule.sh_degree_at(step)

    def loss(self, res: Dict[str, Tensor], tv: TrainView, step: int) -> Dict[str, Tensor]:
        """Every loss term of this step (weighted terms sum to ``total``)."""
        c = self.cfg["loss"]
        terms: Dict[str, Tensor] = {}
        if not self.decomposed:
            terms["total"] = terms["rgb"] = losses.l1_ssim(to_bchw(res["rgb"]), to_bchw(tv.target), c["lambda_ssim"])
            return terms
        R_hat, L_hat, S = to_bchw(res["R"]), to_bchw(res["L"]), to_bchw(tv.S)
        if tv.R is not None:
            sup, sup_terms = losses.supervision_loss(R_hat, L_hat, to_bchw(tv.R), to_bchw(tv.L), S, c["w_r"],
                                                     c["w_l"], c["w_s"], c["lambda_ssim"])
            terms.update(sup_terms)
        else:  # no 2D priors: only the reconstruction is supervised
            terms["sup_rec"] = losses.l1_ssim(R_hat * L_hat, S, c["lambda_ssim"])
            sup = c["w_s"] * terms["sup_rec"]
        terms["tv"] = losses.tv_loss(R_hat)
        terms["sh"] = losses.sh_sparsity_loss(self.model.gaussians.sh_rest, c["sh_reduction"])
        total = sup + c["w_tv"] * terms["tv"] + c["w_sh"] * terms["sh"]
        if self.schedule.enhance_at(step):
            if c["enhance_trains_scene"]:
                out = res
            else:
                # The paper trains the EnhancementNet alone with L_enhance: without this the exposure term would
                # flatten R̂ and L̂ towards E instead of adjusting the gamma.
                out = self.model.enhance(res["R"].detach(), res["L"].detach())
            light = to_bchw(out["L_enh"]) if c["exp_on"] == "illumination" else None
            enh, enh_terms = losses.enhancement_loss(
                to_bchw(out["rgb"]), S, c["w_spa"], c["w_exp"], c["w_col"], c["exposure_E"],
                illumination=light, exp_patch=c["exp_patch"], exp_form=c["exp_form"], spa_form=c["spa_form"],
                scale_invariant=c["enhance_scale_invariant"])
            terms.update(enh_terms)
            total = total + enh
        terms["total"] = total
        return terms

    def train_step(self, step: int, tv: TrainView) -> Dict[str, float]:
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = self._means_lr(step)
        c = self.cfg["loss"]
        # The enhanced image is needed only when L_enhance trains the scene through it (the default detaches).
        enhance = self.decomposed and c["enhance_trains_scene"] and self.schedule.enhance_at(step)
        res = self.model.render(tv.camera, self.active_degree(step), validate=False, enhance=enhance)
        terms = self.loss(res, tv, step)
        terms["total"].backward()
        self.density.update(res["out"], tv.camera.width, tv.camera.height)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        # One host sync per step for every loss value and the finiteness of every parameter: syncs stall the
        # GPU queue, and this loop is launch-bound. A non-finite loss or parameter raises before the next
        # checkpoint, so the last checkpoint on disk is always a good one.
        names = list(terms)
        # Every parameter, the networks' too: a non-finite MLP weight would otherwise reach the step's
        # checkpoint before the next step's loss showed it. A NaN or inf anywhere in a tensor makes its norm
        # non-finite; the multi-tensor norm is a couple of kernels for all of them.
        params = list(self.model.named_parameters())
        norms = torch._foreach_norm([p.detach() for _, p in params])
        checks = torch.stack([terms[k].detach().float() for k in names] + [v.float() for v in norms]).tolist()
        values = dict(zip(names, checks[:len(names)]))
        bad = [k for k, v in values.items() if not math.isfinite(v)]
        if bad:
            raise TrainingDiverged(f"loss term {bad[0]} became {values[bad[0]]} at step {step}; the last good "
                                   f"checkpoint in {self.run / 'checkpoints'} is intact (lower the learning "
                                   "rates or resume from it)")
        for (name, _), norm in zip(params, checks[len(names):]):
            if not math.isfinite(norm):
                label = (f"Gaussian parameter {name[len('gaussians.'):]}" if name.startswith("gaussians.")
                         else f"network parameter {name}")
                raise TrainingDiverged(f"{label} became non-finite at step {step}; the last good checkpoint in "
                                       f"{self.run / 'checkpoints'} is intact")
        size = max(tv.camera.width, tv.camera.height)
        event = self.density.step(step, self.model.gaussians, self.optimizer, size)
        if event:
            values["event"] = event  # type: ignore[assignment]
        return values

    # ---- the loop ----------------------------------------------------------------------------------------
    def checkpoint_state(self) -> Dict:
        return {"step": self.step, "config": self.cfg, "model": self.model.state_dict(),
                "optimizer": self.optimizer.state_dict(), "rng": torch.get_rng_state(),
                "py_rng": random.getstate(), "order": list(self.order), "density": self.density.state_dict(), "normalization": {
                    "center": self.scene.normalization.center, "scale": self.scene.normalization.scale},
                "scene_root": str(self.scene.root), "train_views": [v.name for v in self.scene.train]}

    def save(self) -> Path:
        return save_checkpoint(self.run, self.step, self.checkpoint_state(), self.cfg["checkpoint"]["keep"])

    def train(self, stop_after: Optional[int] = None) -> Dict[str, float]:
        """Train up to ``cfg.steps`` (or ``stop_after`` more steps); returns the last step's loss values."""
        from tqdm import tqdm

        total_steps = self.cfg["steps"]
        end = total_steps if stop_after is None else min(total_steps, self.step + stop_after)
        writer = self._tensorboard()
        log_path = self.run / "train_log.jsonl"
        values: Dict[str, float] = {}
        t0 = time.time()
        bar = tqdm(total=end, initial=self.step, disable=not self.progress, desc="train", dynamic_ncols=True)
        with open(log_path, "a") as log_file:
            while self.step < end:
                if not self.order:
                    self.order = list(range(len(self.views)))
                    random.shuffle(self.order)
                self.step += 1
                values = self.train_step(self.step, self.views[self.order.pop()])
                event = values.pop("event", None)
                if event:
                    log_file.write(json.dumps({"step": self.step, "event": event, "gaussians": len(self.model.gaussians)}) + "\n")
                    log_file.flush()
                if self.step % self.cfg["log"]["every"] == 0 or self.step == end:
                    n = len(self.model.gaussians)
                    bar.set_postfix({k: f"{v:.4f}" for k, v in values.items() if k in
                                     ("total", "sup_rec", "sup_r", "sup_l", "exp", "rgb")} | {"N": n})
                    log_file.write(json.dumps({"step": self.step, "gaussians": n, "seconds": time.time() - t0,
                                               **values}) + "\n")
                    log_file.flush()  # whole lines on disk: a killed run leaves no cut line
                    if writer:
                        for k, v in values.items():
                            writer.add_scalar(f"loss/{k}", v, self.step)
                        writer.add_scalar("gaussians", n, self.step)
                if self.step % self.cfg["checkpoint"]["every"] == 0 or self.step == end:
                    self.save()
                bar.update(1)
        bar.close()
        if writer:
            writer.close()
        values["seconds"] = time.time() - t0
        return values

    def _tensorboard(self):
        if not self.cfg["log"]["tensorboard"]:
            return None
        try:
            from torch.utils.tensorboard import SummaryWriter
        except Exception:  # tensorboard not installed: the JSONL log still has everything
            self.log("tensorboard is not installed: losses are logged to train_log.jsonl only "
                     "(pip install tensorboard)")
            return None
        return SummaryWriter(str(self.run / "tb"))


def write_run_config(run: Path, cfg: Dict, scene_path: Path) -> None:
    """The resolved config of a run (what resume, eval, render and export read back)."""
    data = dict(cfg)
    data["scene"] = str(Path(scene_path).resolve())
    atomic_write_text(run / "config.yaml", yaml.safe_dump(data, sort_keys=False))
