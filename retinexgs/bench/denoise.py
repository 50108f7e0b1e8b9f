"""Time the noise-aware denoiser (decomposer.denoise) on a 12 MP night photo: OpenCV's NLM on the CPU against torch's
on --device, side by side, with each one's PSNR to the clean picture.

    python -m retinexgs.bench denoise --device cuda            # 3000x4000, chroma, 1000 e- / 6 e- read noise
    python -m retinexgs.bench denoise --device cpu --size 750x1000 --repeat 1

The photo is synthetic (smooth colour fields, hard edges, a fine texture; seeded), darkened to an exposure of 0.05
with Poisson–Gaussian noise at --full-well electrons and --read-noise. Each implementation runs once untimed (CUDA's
start-up, OpenCV's threads), then --repeat times; the table gives the median seconds of the whole call (the image
handed over on the CPU and returned there, as the decomposition cache reads it: transfers included) and the PSNR of
the denoised picture (exposure undone, sRGB) to the clean one. ``--json FILE`` also writes the numbers.
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch

from retinexgs.bench.args import image_size
from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear
from retinexgs.fileio import atomic_write_text
from retinexgs.retinex.denoise import METHODS, denoise_linear, noise_model

EXPOSURE = 0.05  # the dark captures' share of the light (retinexgs.data.sensor's default)


def synthetic_photo(h: int, w: int, seed: int = 0) -> torch.Tensor:
    """A clean sRGB photo [h,w,3] in [0,1]: smooth colour gradients, a few hard-edged discs and a striped patch (the
    detail a denoiser must keep), reproducible from ``seed``."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    phase = torch.rand(3, generator=g) * 2 * math.pi
    img = torch.stack([0.45 + 0.3 * torch.sin(2 * math.pi * (1.3 * xx + 0.7 * yy) + p) for p in phase], -1)
    for _ in range(12):
        cy, cx, r = torch.rand(3, generator=g).tolist()
        disc = ((yy - cy) ** 2 + ((xx - cx) * w / h) ** 2) < (0.05 + 0.15 * r) ** 2
        img[disc] = torch.rand(3, generator=g)
    stripes = (torch.sin(2 * math.pi * xx * w / 6.0) > 0).float()[..., None]  # a 6-pixel period
    box = (yy > 0.6) & (yy < 0.8) & (xx > 0.1) & (xx < 0.3)
    img[box] = (0.25 + 0.5 * stripes)[box].expand(-1, 3)
    return img.clamp(0.0, 1.0)


def dark_capture(clean: torch.Tensor, full_well: float, read_noise: float, seed: int = 0) -> torch.Tensor:
    """The linear light [H,W,3] of ``clean`` (sRGB) captured at :data:`EXPOSURE`: Poisson electrons at
    ``full_well`` per unit, Gaussian read noise of ``read_noise`` electrons, clipped to [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    electrons = torch.poisson(srgb_to_linear(clean.double()) * EXPOSURE * full_well, generator=g)
    electrons += torch.randn(electrons.shape, generator=g, dtype=torch.float64) * read_noise
    return (electrons / full_well).clamp(0.0, 1.0).float()


def _psnr(lin: torch.Tensor, clean: torch.Tensor) -> float:
    shown = linear_to_srgb((lin.double() / EXPOSURE).clamp(0.0, 1.0))
    return float(-10.0 * torch.log10(((shown - clean.double()) ** 2).mean()))


def _time(fn, dev: torch.device, repeat: int) -> Tuple[List[float], torch.Tensor]:
    """Seconds of each of ``repeat`` calls of ``fn`` (after one untimed call), and the last result."""
    out = fn()
    seconds = []
    for _ in range(repeat):
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        t0 = time.perf_counter()
        out = fn()
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        seconds.append(time.perf_counter() - t0)
    return seconds, out


def main(argv: Optional[List[str]] = None) -> int:
    """Parse the options, time both implementations, print the table; the exit code."""
    ap = argparse.ArgumentParser(prog="python -m retinexgs.bench denoise", description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu",
                    help="where torch's NLM runs (default: cuda when present)")
    ap.add_argument("--size", type=image_size("HxW", "3000x4000", minimum=32), default=(3000, 4000),
                    help="HxW of the photo (default 3000x4000, 12 MP)")
    ap.add_argument("--method", default="chroma", choices=[m for m in METHODS if m != "none"],
                    help="decomposer.denoise's method (default chroma, what auto picks on raw scenes)")
    ap.add_argument("--full-well", type=float, default=1000.0, help="electrons at raw 1 (default 1000)")
    ap.add_argument("--read-noise", type=float, default=6.0, help="read noise in electrons (default 6)")
    ap.add_argument("--repeat", type=int, default=3, help="timed calls per implementation (default 3)")
    ap.add_argument("--skip-opencv", action="store_true", help="time torch's only (OpenCV's takes ~4 s per MP)")
    ap.add_argument("--json", type=Path, help="also write the numbers to this file")
    args = ap.parse_args(argv)
    if args.repeat < 1 or args.full_well <= 0 or args.read_noise < 0:
        ap.error("--repeat >= 1, --full-well > 0 and --read-noise >= 0 are needed")
    try:
        dev = torch.device(args.device)
        if dev.type == "cuda" and not torch.cuda.is_available():
            raise RuntimeError("no CUDA device")
        torch.empty(1, device=dev)
    except RuntimeError as exc:
        ap.error(f"--device {args.device}: {str(exc).splitlines()[0]}")

    h, w = args.size
    clean = synthetic_photo(h, w)
    noisy = dark_capture(clean, args.full_well, args.read_noise)
    wf = args.full_well
    noise = noise_model(((1.0 / wf,) * 3, ((args.read_noise / wf) ** 2,) * 3))
    runs: Dict[str, Tuple[torch.device, str]] = {}
    if not args.skip_opencv:
        runs["opencv (cpu)"] = (torch.device("cpu"), "opencv")
    runs[f"torch ({dev})"] = (dev, "torch")
    rows = []
    print(f"denoise {args.method}, {h}x{w} ({h * w / 1e6:.1f} MP), {args.full_well:g} e- / {args.read_noise:g} e-, "
          f"noisy PSNR {_psnr(noisy, clean):.2f} dB", flush=True)
    for name, (where, backend) in runs.items():
        seconds, out = _time(lambda: denoise_linear(noisy, noise, args.method, backend=backend, device=where).cpu(),
                             where, args.repeat)
        row = {"implementation": name, "seconds": statistics.median(seconds), "all_seconds": seconds,
               "psnr": _psnr(out, clean)}
        rows.append(row)
        print(f"  {name:<16} {row['seconds']:8.2f} s   PSNR {row['psnr']:.2f} dB", flush=True)
    if args.json:
        info = {"size": [h, w], "method": args.method, "full_well": args.full_well, "read_noise": args.read_noise,
                "device": str(dev), "gpu": torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
                "cpu_threads": torch.get_num_threads(), "host": platform.node(), "rows": rows}
        atomic_write_text(args.json, json.dumps(info, indent=1), "--json")  # never a half-written file
    return 0


if __name__ == "__main__":
    sys.exit(main())
