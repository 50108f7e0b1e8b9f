"""2D proxy of the enhancement, and the decomposition's texture split, on scenes with normal-light pairs.

    python -m retinexgs.bench proxy --scenes DIR... [--configs NAME...] [--views 4] [--device cpu]

For a few training views per scene: LR3M's (R, L) of the dark photo; for each config, the gamma a view gets is
the minimiser (on a grid) of that config's L_enhance on S_enh = R·(L/L_ref)^g, with L_ref the median over the
chosen views of the config's quantile of L; the table gives the PSNR of that S_enh against the normal-light
photo. It is what the 3D model does with perfect 2D priors and a perfect EnhancementNet, in seconds on a CPU:
a way to compare enhancement losses before spending GPU time (it tracked our 3D runs within 2.5 dB on the dev
scenes; experiments/notes/2026-11-23-enhancement-losses.md). No normal-light photo is used except for scoring.

The texture split: the share of the high-pass energy (x − Gaussian blur σ = 2 px, of log luminance) of
log S = log R + log L that lands in log L versus log R. Texture in L is what a gamma on L compresses.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import torch
import torch.nn.functional as F

from retinexgs.evaluate.metrics import psnr, ssim_metric
from retinexgs.kth_value import kth_smallest
from retinexgs.model.tone import tone_map
from retinexgs.train import losses
from retinexgs.run.folder import open_scene
from retinexgs.train.sfm_preview import scene_sfm_denoise
from retinexgs.retinex import decompose
from retinexgs.config.schema import Config
from retinexgs.run.config import load_config
from retinexgs.retinex.lr3m import LR3MParams
from retinexgs.data.scene import scene_label

GAMMAS = torch.linspace(0.1, 1.0, 91)  # the gamma tones' range (the oracles of the gamma on L)
RAW_GAMMAS = torch.linspace(0.05, 1.0, 96)


def quantile(x: torch.Tensor, q: float) -> torch.Tensor:
    flat = x.reshape(-1)
    return kth_smallest(flat, min(flat.numel(), max(1, round(q * flat.numel()))))


def _bchw(x: torch.Tensor) -> torch.Tensor:
    return x.permute(2, 0, 1).unsqueeze(0)


def enhanced_maps(R: torch.Tensor, L: torch.Tensor, ref: float, g: float, cfg: Config):
    """The model's (S_enh, L_enh) from 2D maps, in the config's tone form (:func:`retinexgs.model.tone.tone_map`)."""
    gamma = torch.tensor(float(g), dtype=R.dtype)
    enh = cfg.model.enhancement
    return tone_map(R, L.expand_as(R), torch.tensor(float(ref)), gamma, enh.tone, shoulder=enh.shoulder)


def enhanced(R: torch.Tensor, L: torch.Tensor, ref: float, g: float, cfg: Config) -> torch.Tensor:
    """The model's S_enh from 2D maps (:func:`enhanced_maps`)."""
    return enhanced_maps(R, L, ref, g, cfg)[0]


def proxy_gamma(R: torch.Tensor, L: torch.Tensor, S: torch.Tensor, ref: float, cfg: Config) -> float:
    """The grid gamma minimising ``cfg``'s L_enhance on :func:`enhanced` ([H,W,3] R, S; [H,W,1] L)."""
    c = cfg.loss
    lo, hi = cfg.model.enhancement.gamma_range
    grid = torch.linspace(float(lo), float(hi), 1 + round(100 * (float(hi) - float(lo))))  # steps of 0.01
    best, best_g = float("inf"), float(grid[0])
    enh_cfg = cfg.model.enhancement
    E = float(losses.exposure_target(c, enh_cfg.tone, R * L, enh_cfg.shoulder))  # as training meters
    for g in grid.tolist():
        enh, light = enhanced_maps(R, L, ref, g, cfg)
        total, _ = losses.enhancement_loss(
            _bchw(enh), _bchw(S), c.w_spa, c.w_exp, c.w_col, E,
            illumination=_bchw(light) if c.exp_on == "illumination" else None, exp_patch=c.exp_patch,
            exp_form=c.exp_form, spa_form=c.spa_form, scale_invariant=c.enhance_scale_invariant)
        if float(total) < best:
            best, best_g = float(total), g
    return best_g


def _blur(x: torch.Tensor, sigma: float = 2.0) -> torch.Tensor:
    r = int(3 * sigma)
    t = torch.arange(-r, r + 1, dtype=x.dtype)
    k = torch.exp(-t ** 2 / (2 * sigma ** 2))
    k = k / k.sum()
    y = _bchw(x)
    y = F.conv2d(F.pad(y, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    y = F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return y[0].permute(1, 2, 0)


def texture_split(R: torch.Tensor, L: torch.Tensor) -> float:
    """Share (0..1) of the log-luminance high-pass energy of R·L that lies in L."""
    def hp(x: torch.Tensor) -> torch.Tensor:
        lx = torch.log(x.clamp_min(1e-3))
        return lx - _blur(lx)
    e_l = float(hp(L).square().sum())
    e_r = float(hp(R.mean(-1, keepdim=True)).square().sum())
    return e_l / max(e_l + e_r, 1e-12)


def _views(scene_dir: Path, n: int, cfg: Config) -> List[Tuple[torch.Tensor, torch.Tensor]]:
    """(dark image, normal-light image) of ``n`` evenly spaced paired training views."""

    scene = open_scene(scene_dir, cfg, sfm_denoise=scene_sfm_denoise(cfg.data.sfm_denoise))  # as train opens it
    paired = [v for v in scene.train if v.paired_path is not None] or [v for v in scene.test if v.paired_path]
    if not paired:
        raise SystemExit(f"{scene_dir}: no view has a normal-light pair; the proxy needs them for scoring")
    idx = torch.linspace(0, len(paired) - 1, min(n, len(paired))).round().long().unique().tolist()
    return [(paired[i].image.float(), paired[i].paired_image.float()) for i in idx]


def run(scenes: Sequence[Path], configs: Sequence[str], n_views: int, device: str,
        betas: Sequence[float] = (), overrides: Sequence[str] = ()) -> str:
    """The proxy table and the texture-split table (markdown)."""

    cfgs = {name: load_config([] if name == "default" else [name], overrides) for name in configs}
    base = cfgs[configs[0]]
    rows: Dict[str, List[str]] = {name: [] for name in configs}
    extra: Dict[str, List[str]] = {"LR3M's display rule R·(L/max L)^(1/2.2) (`baseline_pre`'s target)": [],
                                   "best g per view (oracle, L_ref = max)": [],
                                   "best g per view of (R·L/L_ref)^g (oracle, tone signal)": [],
                                   "best g per view of R·L^g (oracle, no L_ref: the paper's formula)": []}
    split_rows: Dict[str, List[str]] = {}
    labels = []
    for scene in scenes:
        labels.append(scene_label(scene))
        views = _views(Path(scene), n_views, base)
        params = dict(base.decomposer.params)
        maps = [(S, H) + tuple(decompose(S.to(device), "lr3m", **params)) for S, H in views]
        maps = [(S, H, R.cpu(), L.cpu()) for S, H, R, L in maps]
        for name, cfg in cfgs.items():
            q = cfg.model.enhancement.ref_quantile
            ref = 1.0 if q is None else float(torch.stack([quantile(L, q) for *_, L in maps]).median())
            scores, ssims, gs = [], [], []
            for S, H, R, L in maps:
                g = proxy_gamma(R, L, S, ref, cfg)
                gs.append(g)
                enh = enhanced(R, L, ref, g, cfg)
                scores.append(psnr(enh, H))
                ssims.append(ssim_metric(enh, H))
            rows[name].append(f"{sum(scores) / len(scores):.2f} / {sum(ssims) / len(ssims):.3f} "
                              f"(g {sum(gs) / len(gs):.2f})")
        ref = float(torch.stack([L.max() for *_, L in maps]).median())
        disp = [psnr((R * (L / L.max()).clamp(0, 1) ** (1 / 2.2)).clamp(0, 1), H) for _, H, R, L in maps]
        best, light = [], []
        for _, H, R, L in maps:
            ln = (L / ref).clamp(1e-3, 1)
            scores = [psnr((R * ln ** g).clamp(0, 1), H) for g in GAMMAS.tolist()]
            k = max(range(len(scores)), key=scores.__getitem__)
            best.append(scores[k])
            light.append(float((ln ** GAMMAS[k]).mean()))  # the enhanced light's level that the truth wants
        sig = [max(psnr(((R * (L / ref).clamp(1e-3, 1)).clamp_min(1e-3) ** g).clamp(0, 1), H)
                   for g in GAMMAS.tolist()) for _, H, R, L in maps]
        extra["best g per view of (R·L/L_ref)^g (oracle, tone signal)"].append(f"{sum(sig) / len(sig):.2f}")
        raw = [max(psnr((R * L.clamp(1e-3, 1) ** g).clamp(0, 1), H) for g in RAW_GAMMAS.tolist())
               for _, H, R, L in maps]
        extra["best g per view of R·L^g (oracle, no L_ref: the paper's formula)"].append(f"{sum(raw) / len(raw):.2f}")
        extra["LR3M's display rule R·(L/max L)^(1/2.2) (`baseline_pre`'s target)"].append(f"{sum(disp) / len(disp):.2f}")
        extra["best g per view (oracle, L_ref = max)"].append(
            f"{sum(best) / len(best):.2f} (light {sum(light) / len(light):.2f})")
        beta0 = float(params.get("beta", LR3MParams().beta))  # free-form per method: LR3M's own default
        for beta in [beta0, *betas]:
            if beta == beta0:
                pairs = [(R, L) for *_, R, L in maps]
            else:
                pairs = [tuple(t.cpu() for t in decompose(S.to(device), "lr3m", **{**params, "beta": beta}))
                         for S, *_ in maps]
            share = sum(texture_split(R, L) for R, L in pairs) / len(pairs)
            split_rows.setdefault(f"LR3M β = {beta:g}", []).append(f"{100 * share:.0f} % / {100 * (1 - share):.0f} %")
    head = "| config (2D proxy: PSNR / SSIM, mean g) | " + " | ".join(labels) + " |\n|" + "---|" * (len(labels) + 1) + "\n"
    body = "".join(f"| `{name}` | " + " | ".join(cells) + " |\n" for name, cells in rows.items())
    body += "".join(f"| {name} | " + " | ".join(cells) + " |\n" for name, cells in extra.items())
    split = ("\n| texture split: high-pass share in L / in R | " + " | ".join(labels) + " |\n|"
             + "---|" * (len(labels) + 1) + "\n"
             + "".join(f"| {name} | " + " | ".join(cells) + " |\n" for name, cells in split_rows.items()))
    return head + body + f"\n{n_views} training views per scene (evenly spaced), PSNR against their normal-light photos.\n" + split


def main(argv: Sequence[str]) -> int:
    ap = argparse.ArgumentParser(prog="python -m retinexgs.bench proxy", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", type=Path, required=True)
    ap.add_argument("--configs", nargs="+", default=["default", "ablations/with_col", "ablations/exp_patch16",
                                                     "ablations/not_scale_invariant", "ablations/ref_p99", "paper"])
    ap.add_argument("--views", type=int, default=4, help="training views per scene (default 4)")
    ap.add_argument("--device", default="cpu", help="where LR3M runs (cpu or cuda)")
    ap.add_argument("--betas", type=float, nargs="*", default=[0.15],
                    help="extra LR3M β values for the texture-split table (default 0.15)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override for every config, e.g. --set decomposer.params.beta=0.15")
    args = ap.parse_args(list(argv))
    for s in args.scenes:
        if not s.is_dir():
            print(f"scene folder {s} does not exist", file=sys.stderr)
            return 2
    print(run(args.scenes, args.configs, args.views, args.device, args.betas, args.set))
    return 0
