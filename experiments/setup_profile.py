"""Where a training's view set-up spends its time (issue 65: the 12 MP raw scene's store took ~2.8 s a view).

Runs ``retinexgs train DATA --set steps=1 ...`` in this process with each set-up stage wrapped in a timer: the
photo's decode for the store (``_read_compact``), the denoised preview LR3M reads (``read_image``: decode, balance,
denoise), the decomposition (``decompose``, synchronised), the cache entry's write (``save_entry``), the view
statistics (``ViewStatistics.add``), the store's consumer waiting for the next item, and the store's own writing.
The stages run on several threads at once: a stage whose busy time is near the set-up's wall time is the one the
rest waits for. Also times a 2 GB write + fsync to the cache folder's disk.

    python experiments/setup_profile.py DATA --out RUN [--device cuda] [--set KEY=VALUE ...]
"""
from __future__ import annotations

import argparse
import os
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable, Dict, List

import torch

BUSY: Dict[str, float] = defaultdict(float)
COUNT: Dict[str, int] = defaultdict(int)
LOCK = threading.Lock()


def timed(name: str, fn: Callable, sync: bool = False) -> Callable:
    def wrapper(*a: Any, **k: Any) -> Any:
        t = time.perf_counter()
        try:
            out = fn(*a, **k)
            if sync and torch.cuda.is_available():
                torch.cuda.synchronize()
            return out
        finally:
            with LOCK:
                BUSY[name] += time.perf_counter() - t
                COUNT[name] += 1
    return wrapper


def timed_iter(name: str, it):
    """An iterator whose next() time (the consumer's wait) is counted as ``name``."""
    it = iter(it)
    while True:
        t = time.perf_counter()
        try:
            x = next(it)
        except StopIteration:
            return
        with LOCK:
            BUSY[name] += time.perf_counter() - t
            COUNT[name] += 1
        yield x


def patch() -> None:
    from retinexgs.retinex import cache
    from retinexgs.train import view_setup, views

    cache.read_image = timed("read_image (decode+balance+denoise, read-ahead threads)", cache.read_image)
    cache.save_entry = timed("save_entry (cache write, behind)", cache.save_entry)
    orig_get = cache.get_decomposer

    def get_decomposer(*a, **k):
        dec = orig_get(*a, **k)
        dec.decompose = timed("decompose (LR3M, synchronised)", dec.decompose, sync=True)
        return dec
    cache.get_decomposer = get_decomposer
    views._read_compact = timed("_read_compact (decode for the store, threads)", views._read_compact)
    views.ViewStatistics.add = timed("ViewStatistics.add", views.ViewStatistics.add, sync=True)
    orig_dv = view_setup.decompose_views
    view_setup.decompose_views = lambda *a, **k: timed_iter("store waits for the next priors", orig_dv(*a, **k))
    orig_ssu = view_setup.stream_set_up

    def stream_set_up(*a, **k):
        it = orig_ssu(*a, **k)
        last = [None]
        for x in timed_iter("store waits for the next item", it):
            yield x
    view_setup.stream_set_up = stream_set_up


def disk_speed(folder: Path, nbytes: int = 2 << 30) -> float:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "disk-speed.tmp"
    block = os.urandom(64 << 20)
    t = time.perf_counter()
    with open(path, "wb") as f:
        for _ in range(nbytes // len(block)):
            f.write(block)
        f.flush()
        os.fsync(f.fileno())
    secs = time.perf_counter() - t
    path.unlink()
    return nbytes / secs / 1e9


def main(argv: List[str] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("--out", required=True)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args(argv)
    patch()
    from retinexgs.cli import main as cli_main
    cmd = ["train", "--data", args.data, "--out", args.out, "--device", args.device, "--quiet", "--set", "steps=1"]
    for s in args.set:
        cmd += ["--set", s]
    t0 = time.perf_counter()
    rc = cli_main(cmd)
    wall = time.perf_counter() - t0
    print(f"train (1 step, set-up and evaluation included): {wall:.1f} s, exit {rc}")
    for name in sorted(BUSY, key=BUSY.get, reverse=True):
        print(f"  {BUSY[name]:8.1f} s busy  {COUNT[name]:5d} calls  {BUSY[name] / max(1, COUNT[name]):7.3f} s each  {name}")
    cache_dir = next((s.split("=", 1)[1] for s in args.set if s.startswith("data.cache_dir=")), args.out)
    print(f"disk: {disk_speed(Path(cache_dir)):.2f} GB/s written with fsync (2 GB)")
    return 0 if rc in (0, None) else int(rc)


if __name__ == "__main__":
    raise SystemExit(main())
