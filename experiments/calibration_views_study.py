"""One view against its truth through the denoiser with three calibrations (issue 64;
notes/2026-11-29-adam-one-launch.md §6).

For each scene folder (a night capture with ``high/`` truth: the raw ladder's RAW and camera-JPEG captures, the demo
scene), the views' noise is measured as training measures it (``denoise_spec`` with ``decomposer.denoise=chroma``),
``--views`` training views spread over the capture are read as training reads them and denoised
(``denoise_view_image``, the photo LR3M would decompose) with the luma/chroma σ taken

- ``model``: from the noise model alone (``calibrate: false``);
- ``calibrated``: the larger of the model's and the measured σ on 4×4 averages, for every component (today's);
- ``chroma-only``: measured for the two chroma components, the model's for the luma (the luma's measurement reads
  texture as noise: §5).

Each result is compared with the view's normal-light photo after ``gt_mean_align`` (PSNR dB / SSIM). One RESULT line
per scene and variant.

    python experiments/calibration_views_study.py SCENE [SCENE ...] [--views 2]
"""
import argparse
import json
from pathlib import Path

import torch

from retinexgs.data.images import read_image_float
from retinexgs.evaluate.metrics import gt_mean_align, psnr, ssim_metric
from retinexgs.retinex import denoise as D
from retinexgs.run.config import load_config
from retinexgs.run.folder import open_scene
from retinexgs.train.view_setup import denoise_spec

_filter = D._filter


def _chroma_only(ycc, method, p, floor, impl="opencv"):
    """``denoise._filter`` with the luma's σ from the model and the chroma's calibrated (a copy of its body)."""
    sig = [floor] + [max(floor, D._measured_sigma(c)) for c in ycc[1:]]
    luma = D._nlm_any(ycc[0], p.h_luma * sig[0], p, impl)
    h, w = ycc.shape[-2:]
    r = int(max(1, min(round(p.radius * w / 640.0), (min(h, w) - 1) // 2)))
    chroma = torch.cat([D._guided(luma[None], c[None], r, p.eps * s * s) for c, s in zip(ycc[1:], sig[1:])])
    return torch.cat([luma[None], chroma])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--views", type=int, default=2)
    args = ap.parse_args()
    cfg = load_config([], ["decomposer.denoise=chroma"])
    for folder in args.scenes:
        scene = open_scene(Path(folder), cfg)
        views = scene.train
        spec = denoise_spec(views, cfg, "cpu")
        picks = [views[round(i * (len(views) - 1) / max(1, args.views - 1))] for i in range(args.views)]
        for variant in ("model", "calibrated", "chroma-only"):
            D._filter = _chroma_only if variant == "chroma-only" else _filter
            params = D.DenoiseParams(calibrate=variant != "model")
            scores = []
            for v in picks:
                image = v.load_target()
                out = D.denoise_view_image(image, spec.noise, "chroma", scene.capture.unclipped, params, "opencv")
                truth_path = next((Path(folder) / "high").glob(Path(v.user_path).stem + ".*"))
                truth = torch.from_numpy(read_image_float(truth_path)).float()
                aligned = gt_mean_align(out, truth)
                scores.append((float(psnr(aligned, truth)), float(ssim_metric(aligned, truth))))
            D._filter = _filter
            mean = [round(sum(s[i] for s in scores) / len(scores), 3) for i in range(2)]
            print("RESULT " + json.dumps({"scene": folder, "variant": variant, "psnr_ssim": mean}), flush=True)


if __name__ == "__main__":
    main()
