"""Compare render-time white-balance estimators off the GPU (issue 53) on dumps of trained runs
(experiments/white_balance_dump.py): each estimator's gains from the dumped training views, applied to the test views'
linear light, encoded as ``render`` encodes (the highlight shoulder, the sRGB curve) and scored against the
truth with eval's colour error (ΔE of the average colours after GT-mean) and GT-mean PSNR, all at half resolution.

    python experiments/white_balance_study.py DUMP.npz... --data DATA_ROOT [--estimators as-trained,grey-edge,...]

A dump's scene is found by its file name's first part (``buu_default_seed0.npz`` -> DATA_ROOT/**/buu).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

import numpy as np
import torch

from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear
from retinexgs.evaluate.metrics import colour_error, gt_mean_align, psnr, ssim
from retinexgs.model.tone import highlight_shoulder
from retinexgs.model.white_balance import grey_edge_gains
from retinexgs.run.config import load_config
from retinexgs.run.folder import open_scene


def _norm(e: np.ndarray) -> np.ndarray:
    """Gains that make an illuminant colour ``e`` (R, G, B) neutral, G kept."""
    return np.array([e[1] / e[0], 1.0, e[1] / e[2]])


def grey_world(imgs: List[np.ndarray]) -> np.ndarray:
    return _norm(np.mean([i.reshape(-1, 3).mean(0) for i in imgs], axis=0))


def shades_of_grey(imgs: List[np.ndarray], p: float = 6.0) -> np.ndarray:
    m = np.mean([(np.clip(i, 0, None).reshape(-1, 3) ** p).mean(0) for i in imgs], axis=0) ** (1 / p)
    return _norm(m)


def grey_edge(imgs: List[np.ndarray]) -> np.ndarray:
    return np.array(grey_edge_gains(torch.from_numpy(i) for i in imgs))


def grey_pixels(imgs: List[np.ndarray], share: float = 0.001, floor: float = 0.02) -> np.ndarray:
    """Grey pixels (Yang, Gao & Li, CVPR 2015): where the local contrast of log light is the same in every channel,
    the surface is achromatic and the pixel shows the light's colour. Contrast = gradient magnitude of log(I)
    per channel after a 3x3 box mean; greyness = std / mean of the three contrasts; the ``share`` greyest pixels
    (above ``floor`` in every channel, not near white, with some contrast) give the light as their mean
    normalised colour."""
    cols, scores = [], []
    for img in imgs:
        x = torch.from_numpy(img).permute(2, 0, 1)[None].double()
        x = torch.nn.functional.avg_pool2d(x, 3, 1, 1, count_include_pad=False)[0].permute(1, 2, 0).numpy()
        lg = np.log(np.clip(x, 1e-6, None))
        gx = np.zeros_like(lg); gy = np.zeros_like(lg)
        gx[:, 1:] = lg[:, 1:] - lg[:, :-1]; gy[1:] = lg[1:] - lg[:-1]
        c = np.sqrt(gx ** 2 + gy ** 2)
        mean = c.mean(-1)
        gi = c.std(-1) / np.maximum(mean, 1e-9)
        ok = (x.min(-1) > floor) & (x.max(-1) < 0.95) & (mean > 0.02)
        scores.append(gi[ok]); cols.append(x[ok])
    s = np.concatenate(scores); c = np.concatenate(cols)
    if len(s) == 0:
        return np.ones(3)
    k = max(1, int(share * sum(i.shape[0] * i.shape[1] for i in imgs)))
    idx = np.argsort(s)[:k]
    sel = c[idx]
    e = (sel / sel.sum(-1, keepdims=True)).mean(0)
    return _norm(e)


ESTIMATORS: Dict[str, Callable[[List[np.ndarray]], np.ndarray]] = {
    "as-trained": lambda imgs: np.ones(3),
    "grey-world": grey_world,
    "shades-of-grey": shades_of_grey,
    "grey-edge": grey_edge,
    "grey-pixels": grey_pixels,
    "grey-pixels-1pc": lambda imgs: grey_pixels(imgs, 0.01),
}


def _half_srgb(img: torch.Tensor) -> torch.Tensor:
    lin = srgb_to_linear(img.double())
    h, w = lin.shape[0] // 2 * 2, lin.shape[1] // 2 * 2
    return linear_to_srgb(lin[:h, :w].reshape(h // 2, 2, w // 2, 2, 3).mean(dim=(1, 3)))


def encoded_test_views(dump, truth: Dict[str, torch.Tensor],
                       tone: Callable[[torch.Tensor], torch.Tensor]) -> Iterator[Tuple[torch.Tensor, torch.Tensor]]:
    """(sRGB render, truth) of each dumped test view that has a truth: the view's linear light through ``tone``,
    the sRGB curve and the clip, both cropped to their common size."""
    for k in dump.files:
        if not k.startswith("test/") or k[5:] not in truth:
            continue
        rgb = linear_to_srgb(tone(torch.from_numpy(dump[k].astype(np.float64)))).clamp(0, 1)
        gt = truth[k[5:]]
        hh, ww = min(rgb.shape[0], gt.shape[0]), min(rgb.shape[1], gt.shape[1])
        yield rgb[:hh, :ww], gt[:hh, :ww]


def dump_study_args(doc: str, argv=None):
    """The dump studies' command line (DUMP.npz... --data ROOT [--set KEY=VALUE]...): the parsed arguments and the
    config the scenes open with."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("dumps", nargs="+", type=Path)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override of the scene")
    args = p.parse_args(argv)
    return args, load_config(overrides=args.set)


def load_dump(dump: Path, data: Path, cfg) -> Tuple[Any, Dict[str, torch.Tensor], float]:
    """A dump's arrays, its scene's test truths at half resolution by view name, and the run's shoulder knee."""
    d = np.load(dump)
    scene = open_scene(_find_scene(data, dump.stem.split("_")[0]), cfg)
    truth = {v.name: _half_srgb(v.paired_image) for v in scene.test if v.paired_path is not None}
    return d, truth, float(d["knee"])


def score_test_views(dump, truth: Dict[str, torch.Tensor], tone: Callable[[torch.Tensor], torch.Tensor],
                     with_ssim: bool = False) -> Tuple[float, float, Optional[float]]:
    """Eval's colour error (ΔE after GT-mean), GT-mean PSNR and, with ``with_ssim``, GT-mean SSIM of the dumped
    test views encoded through ``tone`` (:func:`encoded_test_views`), each the mean over the views."""
    de, ps, ss = [], [], []
    for rgb, gt in encoded_test_views(dump, truth, tone):
        aligned = gt_mean_align(rgb, gt)
        de.append(colour_error(rgb, gt))
        ps.append(psnr(aligned, gt))
        if with_ssim:
            ss.append(float(ssim(aligned.permute(2, 0, 1)[None].float(), gt.permute(2, 0, 1)[None].float())))
    return float(np.mean(de)), float(np.mean(ps)), (float(np.mean(ss)) if with_ssim else None)


def _find_scene(root: Path, name: str) -> Path:
    hits = [p for p in root.rglob(name) if p.is_dir() and (p / "transforms_test.json").is_file()]
    if not hits:
        raise SystemExit(f"no scene folder named {name} under {root}")
    return hits[0]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dumps", nargs="+", type=Path)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--estimators", default=",".join(ESTIMATORS))
    args = p.parse_args(argv)
    cfg = load_config()
    names = args.estimators.split(",")
    print("run | " + " | ".join(f"{n}: ΔE, PSNR | gains" for n in names))
    for dump in args.dumps:
        d, truth, knee = load_dump(dump, args.data, cfg)
        train = [d[k].astype(np.float64) for k in d.files if k.startswith("train/")]
        cells = []
        for n in names:
            g = ESTIMATORS[n](train)
            de, ps, _ = score_test_views(d, truth, lambda v: highlight_shoulder(v * torch.from_numpy(g), knee))
            cells.append(f"{de:.2f}, {ps:.2f} | {g[0]:.3f},{g[2]:.3f}")
        print(f"{dump.stem} | " + " | ".join(cells))
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
