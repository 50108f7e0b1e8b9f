"""Evaluate a trained model on the scene's test views: PSNR / SSIM / LPIPS of the enhanced renders against the
normal-light images, side-by-side PNGs, and ``metrics.json`` (written atomically)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import torch
from PIL import Image

from retinexgs.data import Scene
from retinexgs.evaluate.lpips import MIN_SIZE as LPIPS_MIN_SIZE
from retinexgs.evaluate.metrics import (CHROMA_BAND_PX, black_lift, chroma_band_px, chroma_noises, colour_error,
                                       colour_split, gt_mean_align, lpips_available, lpips_metrics, psnr, ssim_metric)
from retinexgs.fileio import atomic_write, atomic_write_text
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, render_function


def to_uint8(img: torch.Tensor) -> np.ndarray:
    """[H,W,C] float in [0,1] (C = 1 or 3) -> [H,W,3] uint8."""
    x = img.detach().float().clamp(0, 1).cpu()
    if x.shape[-1] == 1:
        x = x.expand(*x.shape[:-1], 3)
    return (x.numpy() * 255 + 0.5).astype(np.uint8)


def save_png(img: torch.Tensor, path: Path, labels: Optional[List[str]] = None) -> None:
    """Write an [H,W,C] image in [0,1] as PNG, atomically. With ``labels`` (one per equal-width panel side by
    side) a strip of :data:`LABEL_ROWS` rows naming the panels is added above the image (its pixels untouched)."""
    arr = to_uint8(img)
    if labels:
        arr = np.concatenate([label_strip(labels, arr.shape[1] // len(labels)), arr], axis=0)
    atomic_write(path, lambda f: Image.fromarray(arr).save(f, format="PNG"))


# Rows of the strip naming the panels above a side-by-side PNG (recorded as "label_rows" in metrics.json: a
# tool that reads the panels' pixels skips them), and its font size.
LABEL_ROWS = 15
_LABEL_FONT = 11


def label_strip(labels: List[str], panel_width: int) -> np.ndarray:
    """[LABEL_ROWS, panel_width * len(labels), 3] uint8: each label in white on black at the left of its panel,
    cut at the panel's edge (Pillow's built-in font)."""
    from PIL import ImageDraw, ImageFont

    try:
        font = ImageFont.load_default(size=_LABEL_FONT)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        font = ImageFont.load_default()
    rows = LABEL_ROWS
    strip = np.zeros((rows, panel_width * len(labels), 3), np.uint8)
    for i, text in enumerate(labels):
        cell = Image.new("RGB", (panel_width, rows))
        ImageDraw.Draw(cell).text((2, 1), text, fill=(255, 255, 255), font=font)
        strip[:, i * panel_width:(i + 1) * panel_width] = np.asarray(cell)
    return strip


def atomic_json(obj: Dict, path: Path) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2))


# The side-by-side PNGs' panel names (the strip above them), in panel order; R and L only for RetinexGS runs.
PANEL_LABELS = ["dark input", "output", "R (reflectance)", "L (illumination)", "normal-light truth"]


def evaluate(render_fn: Callable, scene: Scene, out_dir: Path, use_lpips: bool = True,
             log: Callable[[str], None] = print, extra: Optional[Dict] = None, shard: Tuple[int, int] = (0, 1),
             gather: Optional[Callable[[Any], List[Any]]] = None, sheet_max_side: int = 1920) -> Optional[Dict]:
    """Render every test view with ``render_fn(view) -> dict`` (key ``rgb``, optional ``R``, ``L``), compare
    with its paired normal-light image, write ``out_dir/renders/test/*.png`` and ``out_dir/metrics.json``.

    Returns the metrics, or None (with the reason logged and written) when there is nothing to compare.
    ``shard`` = (rank, ranks) with ``gather`` (every rank's object, in rank order, on every rank): this
    process renders and scores the test views ``i % ranks == rank`` (writing their PNGs); the rows are gathered
    into the test views' order, and rank 0 alone writes metrics.json (the same file as one process writes).
    ``sheet_max_side`` (``eval.sheet_max_side``): the PNGs' panels are shrunk by a whole factor (area mean) until
    each side fits it; the figures are always of the full-size images.
    """
    rank, ranks = shard
    views = [v for v in scene.test if v.paired_path is not None]
    if not views:
        reason = ("the scene has no test views" if not scene.test else
                  "the test views have no paired normal-light images")
        log(f"evaluation skipped: {reason}")
        if rank == 0:
            atomic_json({"skipped": reason, **(extra or {})}, out_dir / "metrics.json")
        return None
    # A test view whose photo is also a training view (the loader warns): its figures are not held-out.
    train_files = {Path(v.source_path or v.image_path).resolve() for v in scene.train}
    test_in_train = sum(Path(v.source_path or v.image_path).resolve() in train_files for v in views)
    rows: List[Dict] = []
    lpips_reason = lpips_available()[1] if use_lpips else ""
    has_maps = False  # the renders have R and L (a RetinexGS run)
    band_top = CHROMA_BAND_PX[1]  # chroma_noise's coarsest scale that fits every test view (metrics.chroma_band_px)
    for view in views[rank::ranks]:
        with torch.no_grad():
            res = render_fn(view)
        # The figures on the render's device (metrics.py keeps its float64 there): on a GPU a 12 MP view's took
        # ~25 s on the host's cores.
        dev = res["rgb"].device
        gt = view.paired_image.to(dev)
        low = view.image.to(dev)
        rgb = res["rgb"].float()
        aligned = gt_mean_align(rgb, gt)  # beside the plain figures: all but the exposure level (metrics.py)
        row = {"view": view.name, "psnr": psnr(rgb, gt), "ssim": ssim_metric(rgb, gt),
               "low_psnr": psnr(low, gt), "low_ssim": ssim_metric(low, gt),
               "psnr_gt_mean": psnr(aligned, gt), "ssim_gt_mean": ssim_metric(aligned, gt),
               "delta_e_gt_mean": colour_error(rgb, gt), "low_delta_e_gt_mean": colour_error(low, gt),
               "black_lift": black_lift(rgb, gt), "low_black_lift": black_lift(low, gt)}
        # issue 64's colour speckle and blotches, on the render's device (its FFTs are the slow part on a CPU)
        row["chroma_noise"], row["low_chroma_noise"] = chroma_noises([res["rgb"], low], gt, device=dev)
        band_top = min(band_top, chroma_band_px(gt.shape[0], gt.shape[1])[1])
        if "rgb_linear" in res:  # the colour error split: the light alone, and what the tone alone costs the truth
            row.update(colour_split(res["rgb_linear"].double(), gt, res["knee"]))
        if use_lpips and not lpips_reason and min(gt.shape[:2]) < LPIPS_MIN_SIZE:
            lpips_reason = f"the test images ({gt.shape[1]}x{gt.shape[0]}) are smaller than LPIPS's " \
                           f"{LPIPS_MIN_SIZE}x{LPIPS_MIN_SIZE} pixels"
        if use_lpips and not lpips_reason:
            # As psnr / ssim: the output, its GT-mean alignment and the dark input, each against the truth, in one
            # batch on the render's device. The output clipped to [0, 1] (the network's range), as its PNG holds it.
            row["lpips"], row["lpips_gt_mean"], row["low_lpips"] = lpips_metrics(
                [rgb.clamp(0.0, 1.0), aligned, low], gt, device=dev)
        rows.append(row)
        panels = [low, rgb]
        labels = PANEL_LABELS[:2]
        has_maps = "R" in res
        if "R" in res:
            # L̂ / L_ref (run.render.render_function): the same rule as `render --maps L` and the viewer
            panels += [res["R"].float().cpu(), res["L_view"].float().cpu()]
            labels = PANEL_LABELS[:4]
        panels.append(gt)
        labels = labels + PANEL_LABELS[4:]
        save_png(torch.cat([shrink_panel(p, sheet_max_side) for p in panels], dim=1),
                 out_dir / "renders" / "test" / f"{Path(view.name).stem}.png", labels)
        # One test view's images at a time: a big capture's test set is not kept in memory.
        view.release_images()
        del panels, low, gt, rgb, aligned
    if gather is not None:  # every rank's rows back in the test views' order (rank r scored r, r + N, ...)
        parts = gather((rows, has_maps, lpips_reason, band_top))
        order = [None] * len(views)
        for r, (part, maps, reason, top) in enumerate(parts):
            order[r::ranks] = part
            has_maps, lpips_reason, band_top = has_maps or maps, lpips_reason or reason, min(band_top, top)
        rows = order
    if lpips_reason:  # LPIPS for every view or for none (a mean over some views would mislead)
        for r in rows:
            for k in ("lpips", "lpips_gt_mean", "low_lpips"):
                r.pop(k, None)
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k != "view"}
    metrics = {"mean": mean, "views": rows, "panels": "low input | output | R̂ | L̂ / L_ref | ground truth"
               if has_maps else "low input | output | ground truth",
               "label_rows": LABEL_ROWS,  # the PNGs' strip naming the panels, above them
               # the scales chroma_noise measured (px): 2-32, or less where a test view is under 64 px
               "chroma_noise_band_px": [CHROMA_BAND_PX[0], band_top]}
    if test_in_train:
        metrics["test_in_train"] = test_in_train
    metrics.update(extra or {})
    if use_lpips and "lpips" not in mean:
        metrics["lpips_unavailable"] = lpips_reason
        log(f"LPIPS not reported: {lpips_reason}")
    if rank == 0:
        atomic_json(metrics, out_dir / "metrics.json")
    log(f"test views: PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.3f}"
        + (f", LPIPS {mean['lpips']:.3f}" if "lpips" in mean else "")
        + f"  (brightness aligned to the truth, GT-mean: {mean['psnr_gt_mean']:.2f} dB, {mean['ssim_gt_mean']:.3f}"
        + (f", {mean['lpips_gt_mean']:.3f}" if "lpips_gt_mean" in mean else "") + ")"
        + f"  (chroma noise {mean['chroma_noise']:.2f}, 1 = the truth's)"
        + f"  (low input: PSNR {mean['low_psnr']:.2f} dB, SSIM {mean['low_ssim']:.3f})"
        + (f"  (not held-out: {test_in_train} of {len(views)} test views are training views)" if test_in_train
           else ""))
    return metrics


def shrink_panel(img: torch.Tensor, max_side: int) -> torch.Tensor:
    """One contact-sheet panel on the CPU as [H,W,3] float: an [H,W,C] image (C = 1 is repeated) shrunk by the
    smallest whole factor that brings both sides to ``max_side`` or less (the mean of each factor × factor block;
    edge rows and columns past a whole block dropped). A 12 MP view's five panels would make a 60 MP PNG that takes
    seconds to write and is too large to look at; `retinexgs render` writes full-size images."""
    x = img.detach().float()[..., :3]
    if x.shape[-1] == 1:
        x = x.expand(*x.shape[:-1], 3)
    k = -(-max(x.shape[0], x.shape[1]) // max(int(max_side), 1))
    if k > 1:
        x = torch.nn.functional.avg_pool2d(x.permute(2, 0, 1)[None], k)[0].permute(1, 2, 0)
    return x.cpu()


def eval_run(run_dir: Path, device: Optional[str] = None, log: Callable[[str], None] = print) -> Optional[Dict]:
    """Re-evaluate a saved run (rewrites metrics.json and renders/test)."""
    cfg, scene, model, step = load_run(run_dir, device)
    return evaluate(render_function(model, cfg, active_sh_degree(cfg, step), linear=True), scene, Path(run_dir),
                    cfg.eval.lpips, log, sheet_max_side=cfg.eval.sheet_max_side)
