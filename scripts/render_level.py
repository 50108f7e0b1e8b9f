"""How much of a run's test error is the exposure level, from the PNGs `evaluate` writes (a development tool, CPU).

    python scripts/render_level.py RUN/renders/test [...]

Each PNG holds the panels "low | output | R̂ | L̂ | truth" (``metrics.json``'s "panels"). Per view, the output is
re-exposed in linear light, srgb(c·lin(output)) (what a change of the exposure gain k does, up to clipping), and
scored against the truth:
- ``as rendered``: c = 1;
- ``best gain``: the c with the best PSNR (a grid over 0.5-2), i.e. what any exposure rule could reach at most;
- ``mean 0.5`` and ``centre 0.5``: the c at which the image's mean, or a centre-weighted mean (a Gaussian weight of
  σ = 0.35 of the frame, as a camera's centre-weighted meter), equals 0.5. Neither target looks at the truth.
Also printed: the mean of the output and of the truth, and the 1st percentile of both (the black level).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(y: np.ndarray) -> np.ndarray:
    y = np.clip(y, 0.0, 1.0)
    return np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(np.maximum(y, 1e-12), 1 / 2.4) - 0.055)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(((a - b) ** 2).mean()))


def centre_weights(h: int, w: int, sigma: float = 0.35) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return np.exp(-(((yy - h / 2) / (sigma * h)) ** 2 + ((xx - w / 2) / (sigma * w)) ** 2) / 2)


def gain_for(stat, z: np.ndarray, target: float) -> float:
    """Bisection for c with stat(srgb(c·z)) = target (the statistic grows with c)."""
    lo, hi = 0.2, 5.0
    for _ in range(40):
        c = (lo + hi) / 2
        lo, hi = (c, hi) if stat(linear_to_srgb(c * z)) < target else (lo, c)
    return (lo + hi) / 2


def main(folders: list) -> None:
    for folder in folders:
        rows = []
        for f in sorted(Path(folder).glob("*.png")):
            im = np.asarray(Image.open(f).convert("RGB"), dtype=np.float64) / 255
            w = im.shape[1] // 5
            if im.shape[1] != 5 * w:
                sys.exit(f"{f}: not five panels side by side (low | output | R | L | truth)")
            out, truth = im[:, w:2 * w], im[:, 4 * w:]
            z = srgb_to_linear(out)
            cw = centre_weights(*out.shape[:2])
            centre = lambda x: float((x.mean(-1) * cw).sum() / cw.sum())  # noqa: E731
            best = max((psnr(linear_to_srgb(c * z), truth), c) for c in np.linspace(0.5, 2.0, 151))
            rows.append([psnr(out, truth), best[0], best[1],
                         psnr(linear_to_srgb(gain_for(np.mean, z, 0.5) * z), truth),
                         psnr(linear_to_srgb(gain_for(centre, z, 0.5) * z), truth),
                         out.mean(), truth.mean(), np.percentile(out, 1), np.percentile(truth, 1)])
            r = rows[-1]
            print(f"  {f.name:10s} as rendered {r[0]:.2f}  best gain {r[1]:.2f} (c = {r[2]:.2f})  mean 0.5 {r[3]:.2f}"
                  f"  centre 0.5 {r[4]:.2f}  mean {r[5]:.3f} / truth {r[6]:.3f}  p1 {r[7]:.3f} / truth {r[8]:.3f}")
        if rows:
            m = np.mean(rows, axis=0)
            print(f"{folder}: as rendered {m[0]:.2f}  best gain {m[1]:.2f}  mean 0.5 {m[3]:.2f}  centre 0.5 {m[4]:.2f}"
                  f"  mean {m[5]:.3f} / truth {m[6]:.3f}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
