"""Re-train only the enhancement of trained runs under other configs, and score each on the test views.

    python -m retinexgs.bench retone --runs RUN... --configs NAME... [--steps 2000] [--seeds 1] [--device cpu]

With ``loss.enhance_trains_scene: false`` (the default) L_enhance reaches only the EnhancementNet: R̂ and L̂
are detached in its path, so the 3D scene a run learns does not depend on the enhancement's config. An
enhancement variant (tone form, gamma range, exposure rule, the L_enhance weights) can then be compared on one
trained scene: for each config a fresh EnhancementNet is trained with that config's L_enhance on the run's
renders of its training views (one view per step, Adam at the config's ``lr.enhancement``, as the trainer does),
then the test views are enhanced and scored against their normal-light photos. Each row shares the run's
reconstruction, so the differences between rows are the enhancement's alone; it is how a variant is measured
where training every scene per variant is not affordable (a CPU). The trainer's own schedule differs (it
trains the net for the last 70 % of the run while R̂ and L̂ still change), so the run's own metrics are printed
beside the ``default`` row as a check.

A config may change only the enhancement: ``model.enhancement`` (not ``ref_quantile``: L_ref comes from the
2D priors at training time), the L_enhance keys of ``loss`` and ``lr.enhancement``; anything else needs a new
training and is refused by name.
"""
from __future__ import annotations

import argparse
import json
import random
import sys
from pathlib import Path
from typing import Dict, Iterator, List, Sequence, Tuple

import torch

from retinexgs.errors import UserError
from retinexgs.evaluate.metrics import psnr, ssim_metric
from retinexgs.config import plain
from retinexgs.config.schema import Config
from retinexgs.run.config import load_config
from retinexgs.train.losses import to_bchw
from retinexgs.train.trainer import enhancement_objective
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, view_camera

ENHANCEMENT_LOSS_KEYS = ("w_spa", "w_exp", "w_col", "exposure_E", "exp_on", "exp_patch", "exp_form",
                         "exp_highlight_share", "spa_form",
                         "enhance_scale_invariant")


def _leaves(d: Dict, prefix: Tuple[str, ...] = ()) -> Iterator[Tuple[Tuple[str, ...], object]]:
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, prefix + (k,))
        else:
            yield prefix + (k,), v


def _allowed(key: Tuple[str, ...]) -> bool:
    if key[:2] == ("model", "enhancement"):
        return key[2:] != ("ref_quantile",)
    return (key[:1] == ("loss",) and key[1:] and key[1] in ENHANCEMENT_LOSS_KEYS) or key == ("lr", "enhancement")


def variant_config(run_cfg: Config, name: str, overrides: Sequence[str] = ()) -> Config:
    """The run's config with config file ``name`` ("default": none) and then ``overrides`` (KEY=VALUE) applied,
    checked to change only the enhancement (UserError naming the first other key it changes)."""

    if name == "default" and not overrides:
        return run_cfg.model_copy(deep=True)
    cfg = load_config([] if name == "default" else [name], list(overrides), base=run_cfg,
                      base_label="the run's config")
    before = dict(_leaves(plain(run_cfg)))  # compared as data, key path by key path
    for key, value in _leaves(plain(cfg)):
        if before.get(key, object()) != value and not _allowed(key):
            raise UserError(f"config {name} changes {'.'.join(key)} ({before.get(key)!r} -> {value!r}): only the "
                            f"enhancement can be re-trained on a trained scene; train it with --config {name}")
    return cfg


def retone(model, cfg: Config, train_maps: List[Tuple[torch.Tensor, torch.Tensor, torch.Tensor]], steps: int,
           seed: int = 0):
    """A copy of ``model`` whose EnhancementNet (and tone form) follow ``cfg`` and is trained ``steps`` steps on
    ``train_maps`` [(R̂, L̂, S)] with ``cfg``'s L_enhance; the scene's parameters are shared, not trained."""

    if cfg.loss.enhance_trains_scene:
        raise UserError("loss.enhance_trains_scene is true: the enhancement then changes the scene, re-train it")
    torch.manual_seed(seed)
    rng = random.Random(seed)
    m = model.with_enhancement(cfg.model.enhancement)
    opt = torch.optim.Adam(m.enhancement.parameters(), lr=cfg.lr.enhancement)
    for _ in range(steps):
        R, L, S = train_maps[rng.randrange(len(train_maps))]
        total, _ = enhancement_objective(m, cfg.loss, R, L, to_bchw(S))
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
    return m


def run(runs: Sequence[Path], configs: Sequence[str], steps: int, device: str, seeds: Sequence[int] = (0,),
        overrides: Sequence[str] = ()) -> str:
    """The markdown table: per run and config, test PSNR / SSIM (mean ± sample std over the EnhancementNet's
    ``seeds``: its initialisation and view order; the scene is the run's) and the mean predicted gamma."""

    lines = ["| run | config | PSNR / SSIM (± over enhancement seeds) | mean g |", "|---|---|---|---|"]
    for run_dir in runs:
        cfg, scene, model, step = load_run(run_dir, device)
        if cfg.method != "retinexgs":
            raise UserError(f"{run_dir} is a {cfg.method} baseline: it has no enhancement to re-train")
        degree = active_sh_degree(cfg, step)
        model.eval()

        def maps(views):
            out = []
            with torch.no_grad():
                for v in views:
                    res = model.render(view_camera(v), degree, enhance=False)
                    out.append((res["R"], res["L"], v.image.to(res["R"])))
            return out

        train_maps = maps(scene.train)
        tests = [v for v in scene.test if v.paired_path is not None]
        if not tests:
            raise UserError(f"{run_dir}: the scene's test views have no normal-light photos to score against")
        test_maps = maps(tests)
        metrics = Path(run_dir) / "metrics.json"
        own = json.loads(metrics.read_text()).get("mean", {}) if metrics.is_file() else {}
        if "psnr" in own:
            lines.append(f"| {Path(run_dir).name} | (the run's own, trained with the scene) | "
                         f"{own['psnr']:.2f} / {own['ssim']:.3f} | – |")
        for name in configs:
            variant = variant_config(cfg, name, overrides)
            per_seed = []
            for seed in seeds:
                m = retone(model, variant, train_maps, steps, seed)
                scores = []
                with torch.no_grad():
                    for (R, L, _), v in zip(test_maps, tests):
                        out = m.enhance(R, L)
                        rgb, gt = out["rgb"].float().cpu(), v.paired_image.float().cpu()
                        scores.append((psnr(rgb, gt), ssim_metric(rgb, gt), float(out["gamma"].mean())))
                per_seed.append(torch.tensor(scores, dtype=torch.float64).mean(0))
            t = torch.stack(per_seed)
            sd = t.std(0) if len(seeds) > 1 else torch.zeros(3, dtype=torch.float64)
            lines.append(f"| {Path(run_dir).name} | `{name}` | {t[:, 0].mean():.2f} ± {sd[0]:.2f} / "
                         f"{t[:, 1].mean():.3f} ± {sd[1]:.3f} | {t[:, 2].mean():.2f} |")
            print(lines[-1], file=sys.stderr, flush=True)
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str]) -> int:
    ap = argparse.ArgumentParser(prog="python -m retinexgs.bench retone", description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", type=Path, required=True, help="trained RetinexGS run folders")
    ap.add_argument("--configs", nargs="+", default=["default"], help="config names (default: the run's own)")
    ap.add_argument("--steps", type=int, default=2000, help="EnhancementNet steps per config (default 2000)")
    ap.add_argument("--seeds", type=int, default=1, help="EnhancementNet seeds 0..N-1 per config (default 1)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="enhancement override for every config, e.g. --set model.enhancement.per_view=false")
    args = ap.parse_args(list(argv))
    if args.steps < 1 or args.seeds < 1:
        print("--steps and --seeds must be at least 1", file=sys.stderr)
        return 2
    try:
        print(run(args.runs, args.configs, args.steps, args.device, range(args.seeds), args.set))
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0
