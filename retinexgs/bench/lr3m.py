"""Benchmark the Retinex decomposers on a scene with paired ``low/`` and ``high/`` photos.

    python -m retinexgs.bench.lr3m --data /path/to/fox-dark --device cpu --limit 3

For each method: seconds per image (wall clock; CUDA synchronised; the first image is also timed) and
PSNR/SSIM of the viewable enhancement S' = R∘(L/max L)^{1/2.2} against ``high/``, next to PSNR/SSIM of
the raw low photo. Prints one table; ``--json FILE`` also writes the numbers.

Memory: each image's peak during its decomposition beyond what was held before it: allocated bytes on CUDA, the
process's resident set on the CPU (Linux: the peak reset through /proc/self/clear_refs; elsewhere nan). ``--resize HxW``
decomposes the photos resized (bilinear) to that size, e.g. 3000x4000 for a 12 MP photo, as a memory probe.
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Dict, List, Optional

import torch

from retinexgs.bench.args import image_size
from retinexgs.retinex import enhance_for_viewing, get_decomposer
from retinexgs.retinex.cache import IMAGE_EXTENSIONS, read_image, resolve_device
from retinexgs.evaluate.metrics import psnr, ssim_metric as ssim


def _pairs(scene: Path, limit: int) -> List[tuple]:
    low, high = scene / "low", scene / "high"
    if not low.is_dir() or not high.is_dir():
        sys.exit(f"{scene} needs low/ and high/ subfolders with the same file names")
    names = sorted(p.name for p in low.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and (high / p.name).is_file())
    if not names:
        sys.exit(f"no paired images in {low} and {high}")
    if limit > 0:
        names = names[:limit]
    return [(low / n, high / n) for n in names]


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _resize(img: torch.Tensor, size) -> torch.Tensor:
    """[H,W,3] in [0,1] resized (bilinear) to ``size`` = (h, w), or as it is for None."""
    if size is None or tuple(img.shape[:2]) == tuple(size):
        return img
    x = torch.nn.functional.interpolate(img.permute(2, 0, 1)[None], size=size, mode="bilinear", align_corners=False)
    return x[0].permute(1, 2, 0).clamp(0.0, 1.0).contiguous()


def _proc_status_gib(key: str) -> Optional[float]:
    """A ``VmRSS`` / ``VmHWM`` line of /proc/self/status in GiB (Linux), or None."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 2 ** 20
    except (OSError, ValueError, IndexError):
        pass
    return None


def _start_host_peak() -> Optional[float]:
    """Reset the process's peak RSS (Linux: ``5`` to /proc/self/clear_refs) and return the RSS now, GiB; None
    where the peak cannot be reset (then the memory column is left empty on the CPU)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return None
    return _proc_status_gib("VmRSS")


def _param(text: str) -> tuple:
    """KEY=VALUE with VALUE an int, a float, true/false or else a string."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, e.g. tile_pixels=1000000000, got {text!r}")
    for cast in (int, float):
        try:
            return key.strip(), cast(raw)
        except ValueError:
            pass
    return key.strip(), {"true": True, "false": False}.get(raw.strip().lower(), raw)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="scene folder with low/ and high/")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--limit", type=int, default=3, help="number of image pairs (0 = all)")
    ap.add_argument("--methods", default="lr3m,lime", help="comma-separated methods")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = leave as is)")
    ap.add_argument("--json", default=None, help="also write the results to this JSON file")
    ap.add_argument("--resize", type=image_size("HxW", "3000x4000"), default=None, metavar="HxW",
                    help="decompose the photos resized to HxW (a memory and time probe for big photos)")
    ap.add_argument("--param", type=_param, action="append", default=[], metavar="KEY=VALUE",
                    help="a decomposer parameter for every method, e.g. tile_pixels=1000000000 (a 12 MP photo whole)")
    ap.add_argument("--metrics", action=argparse.BooleanOptionalAction, default=True,
                    help="PSNR / SSIM against high/ (--no-metrics: time and memory alone; SSIM of a 12 MP photo "
                         "takes minutes on the CPU)")
    args = ap.parse_args(argv)
    params = dict(args.param)
    try:
        decomposers = [get_decomposer(m.strip(), **params) for m in args.methods.split(",") if m.strip()]
    except ValueError as exc:
        ap.error(str(exc))

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    dev = resolve_device(args.device)
    pairs = _pairs(Path(args.data), args.limit)
    print(f"# {len(pairs)} image(s) from {args.data}, device {dev}"
          + (f" ({torch.cuda.get_device_name(dev)})" if dev.type == "cuda" else
             f" ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)")
          + f", torch {torch.__version__}")
    lows = [_resize(read_image(lo), args.resize) for lo, _ in pairs]
    # Without metrics the truths are not read (a resized 12 MP truth is 144 MB for nothing).
    highs = [_resize(read_image(hi), args.resize) if args.metrics else None for _, hi in pairs]
    nan = float("nan")
    raw_p = [float(psnr(lo, hi)) if args.metrics else nan for lo, hi in zip(lows, highs)]
    raw_s = [float(ssim(lo, hi)) if args.metrics else nan for lo, hi in zip(lows, highs)]
    rows: Dict[str, Dict[str, float]] = {
        "raw low": {"s_per_image": nan, "psnr": statistics.mean(raw_p), "ssim": statistics.mean(raw_s)}}
    for dec in decomposers:
        method = dec.name
        times, ps, ss, cpu, mem = [], [], [], [], []
        for (lo_path, _), lo, hi in zip(pairs, lows, highs):
            x = lo.to(dev)
            _sync(dev)
            if dev.type == "cuda":
                held = torch.cuda.memory_allocated(dev)
                torch.cuda.reset_peak_memory_stats(dev)
            else:
                rss = _start_host_peak()
            t0, c0 = time.perf_counter(), time.process_time()
            r, l = dec.decompose(x)
            _sync(dev)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            if dev.type == "cuda":
                mem.append((torch.cuda.max_memory_allocated(dev) - held) / 2 ** 30)
            else:
                peak = _proc_status_gib("VmHWM") if rss is not None else None
                mem.append(nan if peak is None else peak - rss)
            if args.metrics:
                enh = enhance_for_viewing(r, l, 2.2).cpu()
                ps.append(float(psnr(enh, hi)))
                ss.append(float(ssim(enh, hi)))
            else:
                ps.append(nan)
                ss.append(nan)
            del r, l
            print(f"  {method:5s} {lo_path.name} {tuple(x.shape[:2])}: {times[-1]:7.2f} s (cpu {cpu[-1]:6.1f} s)  "
                  f"PSNR {ps[-1]:6.2f} dB  SSIM {ss[-1]:.3f}  memory {mem[-1]:.2f} GiB "
                  f"({mem[-1] * 2 ** 30 / (x.shape[0] * x.shape[1]):.0f} B/px)", flush=True)
        rows[method] = {"s_per_image": statistics.mean(times), "s_median": statistics.median(times),
                        "cpu_s_per_image": statistics.mean(cpu), "psnr": statistics.mean(ps),
                        "ssim": statistics.mean(ss), "key": dec.cache_key(), "memory_gib": max(mem),
                        "memory": "peak CUDA allocation beyond the held" if dev.type == "cuda"
                        else "peak RSS growth during the decomposition"}
    print()
    print("| method | s / image (mean) | PSNR vs high (dB) | SSIM vs high | ΔPSNR vs raw low | memory (GiB) |")
    print("|---|---|---|---|---|---|")
    base = rows["raw low"]["psnr"]
    for name, row in rows.items():
        secs = "—" if name == "raw low" else f"{row['s_per_image']:.2f}"
        delta = "—" if name == "raw low" else f"{row['psnr'] - base:+.2f}"
        memory = f"{row['memory_gib']:.2f}" if "memory_gib" in row else "—"
        quality = f"{row['psnr']:.2f} | {row['ssim']:.3f}" if args.metrics else "— | —"
        delta = delta if args.metrics else "—"
        print(f"| {name} | {secs} | {quality} | {delta} | {memory} |")
    if args.json:
        meta = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "device": str(dev),
                "images": [str(lo) for lo, _ in pairs], "threads": torch.get_num_threads(),
                "resize": list(args.resize) if args.resize else None, "params": params,
                "torch": torch.__version__}
        finite = {name: {k: (None if isinstance(v, float) and v != v else v) for k, v in row.items()}
                  for name, row in rows.items()}  # NaN (not measured) as null: standard JSON
        Path(args.json).write_text(json.dumps({"meta": meta, "rows": finite}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
