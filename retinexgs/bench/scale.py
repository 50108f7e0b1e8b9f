"""Large-scene benchmark: one big dark scene trained on 1, 2 and 4 GPUs at equal views seen, side by side:
views/s, steps/s, peak GPU memory per rank, host RSS, time to first step, PSNR / SSIM, speed-up and efficiency.

    python -m retinexgs.bench scale [--scene DIR | --views 1000 --width 1920 --height 1080 --test-views 8]
        [--gpus 1,2,4] [--views-seen 2000] [--config NAME] [--set KEY=VALUE ...] [--decompose once|none]
        [--device auto|cuda|cpu] [--out DIR]

The scene: ``--scene DIR`` trains a scene as it is; without it, a synthetic dark scene
(:mod:`retinexgs.demo.large`: the demo scene at any size) is generated into ``--scenes-dir`` (default
``$TMPDIR/retinexgs-scale``), one view at a time, on the GPU when there is one, and reused by later calls with the
same parameters (``scene_params.json`` in the folder).

Before training, the memory the scene would need if every view were preloaded is printed, by issue 34's formulas
for today's trainer (GPU 28 B per view-pixel after set-up, 44 B once each view was used; host set-up peak 28 B/px).

The decomposition runs once, before the trainings and untimed (``--decompose once``, the default:
``python -m retinexgs decompose`` with the same --config/--set, cached in the scene folder and shared by every rank
count and by later calls), because the figures should describe the config as it trains, 2D priors included (their
memory and their loss terms are part of what scales). ``--decompose none`` trains without priors
(``decomposer.method=none``) for a quick run: LR3M costs about 24 µs of CPU per pixel, some 9 minutes on an H100 for
1000 views at 1080p.

Each rank count N trains ``ceil(views_seen / (N × views_per_rank))`` steps from scratch: N = 1 as
``python -m retinexgs train``, N > 1 as ``python -m torch.distributed.run --standalone --nproc_per_node N -m
retinexgs train`` (where this build has ``retinexgs.train.distributed``; otherwise that N is skipped with a note).
The figures come from each run's ``metrics.json`` ("train" and "mean"); a key the training does not record prints
as "–" with a note, or is computed (views/s from steps / train_seconds) or measured here (host RSS: the largest
process of the launched tree, from ``wait4``), marked as such. Writes ``OUT/scale.md`` and ``OUT/scale.json``
after every run (a cut-off call keeps what finished), the runs in ``OUT/runs/gpusN`` (logs beside them).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import math
import multiprocessing
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import torch
from PIL import Image

from retinexgs.demo.large import FORMATS, PARAMS_FILE, default_folder_name, ensure_large_scene, scene_params
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write_text

GB = 2**30  # as metrics.json's *_gb keys (torch.cuda.max_memory_allocated() / 2**30)

# Issue 34's figures for today's trainer, bytes per training view-pixel (every view preloaded).
GPU_AFTER_SETUP = 28  # S, R and L as float32
GPU_AFTER_USE = 44  # + pack()'s [H,W,9] and the edge maps, kept once a view has been used
HOST_SETUP_PEAK = 28  # the photos as float32 plus every view's priors at once
HOST_RSS_BASE, HOST_RSS_PER_PX = 347 * 2**20, 32  # the CPU fit of set-up RSS
CACHE_PER_PX = 8  # the decomposition cache on disk


# ----------------------------------------------------------------------------------------------------
# Plan

def parse_gpus(text: str) -> List[int]:
    """``1,2,4`` -> [1, 2, 4] (positive, in the given order, duplicates dropped)."""
    try:
        values = [int(s) for s in text.replace(" ", ",").split(",") if s.strip()]
    except ValueError:
        raise ValueError(f"--gpus {text!r}: a comma-separated list of rank counts, e.g. 1,2,4") from None
    if not values or min(values) < 1:
        raise ValueError(f"--gpus {text!r}: every rank count must be >= 1")
    return list(dict.fromkeys(values))


def steps_for(views_seen: int, ranks: int, views_per_rank: int = 1) -> int:
    """Steps that show at least ``views_seen`` views with ``ranks × views_per_rank`` views a step."""
    return max(1, math.ceil(views_seen / (ranks * views_per_rank)))


def has_distributed() -> bool:
    """Whether this build has the multi-GPU training (``retinexgs.train.distributed``), looked up as a file: the
    benchmarks never import ``retinexgs.train`` (docs/architecture.md)."""
    spec = importlib.util.find_spec("retinexgs")
    roots = list(spec.submodule_search_locations or []) if spec is not None else []
    return any((Path(r) / "train" / "distributed.py").is_file()
               or (Path(r) / "train" / "distributed" / "__init__.py").is_file() for r in roots)


def _image_file(scene: Path, file_path: str) -> Path:
    p = scene / file_path
    if p.suffix.lower() in (".png", ".jpg", ".jpeg") or p.is_file():
        return p
    for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG"):
        if p.with_name(p.name + ext).is_file():
            return p.with_name(p.name + ext)
    return p


def scene_size(scene: Path) -> Tuple[int, int, int]:
    """(training views, width, height) of a scene folder: from transforms_train.json where there is one (sizes
    from its w/h or its first image), else the photos in low/, images/ or the folder (their first one's size)."""
    tj = scene / "transforms_train.json"
    if tj.is_file():
        meta = json.loads(tj.read_text())
        frames = meta.get("frames") or []
        if not frames:
            raise UserError(f"{tj} lists no frames")
        w, h = meta.get("w"), meta.get("h")
        if not (w and h):
            with Image.open(_image_file(scene, frames[0]["file_path"])) as im:
                w, h = im.size
        return len(frames), int(w), int(h)
    for d in (scene / "low", scene / "images", scene):
        photos = sorted(p for p in d.glob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg")) if d.is_dir() else []
        if photos:
            with Image.open(photos[0]) as im:
                return len(photos), im.size[0], im.size[1]
    raise UserError(f"{scene}: no transforms_train.json and no photos in low/, images/ or the folder")


# ----------------------------------------------------------------------------------------------------
# Memory estimate

def _gpu_total_bytes() -> Optional[int]:
    """The first GPU's memory from nvidia-smi (no CUDA context in this process: rank 0 shares that GPU)."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=memory.total", "--format=csv,noheader,nounits"],
                             capture_output=True, text=True, timeout=20)
        return int(float(out.stdout.split()[0])) * 2**20 if out.returncode == 0 and out.stdout.split() else None
    except (OSError, ValueError, subprocess.SubprocessError):
        return None


def _host_total_bytes() -> Optional[int]:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def estimate(views: int, width: int, height: int, gpu_bytes: Optional[int] = None,
             host_bytes: Optional[int] = None) -> Dict:
    """What a run needs if every training view is preloaded, by issue 34's formulas for today's trainer (bytes)."""
    px = views * width * height
    est = {"view_pixels": px, "views": views, "width": width, "height": height,
           "gpu_after_setup": GPU_AFTER_SETUP * px, "gpu_after_use": GPU_AFTER_USE * px,
           "host_setup_peak": HOST_SETUP_PEAK * px, "host_rss": HOST_RSS_BASE + HOST_RSS_PER_PX * px,
           "decomposition_cache": CACHE_PER_PX * px, "gpu_total": gpu_bytes, "host_total": host_bytes}
    est["fits_gpu"] = None if gpu_bytes is None else est["gpu_after_use"] <= gpu_bytes
    est["fits_host"] = None if host_bytes is None else est["host_setup_peak"] <= host_bytes
    if gpu_bytes:
        est["views_fitting_gpu"] = int(gpu_bytes // (GPU_AFTER_USE * width * height))
    return est


def _size(b: float) -> str:
    return f"{b / GB:.1f} GB" if b >= GB else f"{b / 2**20:.1f} MB"


def format_estimate(est: Dict) -> str:
    gb = _size
    fit = lambda ok, total: "" if ok is None else (  # noqa: E731
        f" (this machine: {gb(total)}: {'fits' if ok else 'does NOT fit'})")
    lines = [f"memory if every view were preloaded (issue 34's formulas for today's trainer), "
             f"{est['views']} training views at {est['width']}x{est['height']} = {est['view_pixels']:,} "
             "view-pixels:",
             f"  GPU   {GPU_AFTER_SETUP} B/px after set-up = {gb(est['gpu_after_setup'])}; {GPU_AFTER_USE} B/px once "
             f"each view was used = {gb(est['gpu_after_use'])}{fit(est['fits_gpu'], est['gpu_total'])}"
             + (f"; about {est['views_fitting_gpu']} views of this size fit" if "views_fitting_gpu" in est else ""),
             f"  host  set-up peak {HOST_SETUP_PEAK} B/px = {gb(est['host_setup_peak'])}"
             f"{fit(est['fits_host'], est['host_total'])}; set-up RSS 347 MiB + {HOST_RSS_PER_PX} B/px = "
             f"{gb(est['host_rss'])} (per process that loads every view)",
             f"  disk  the decomposition cache {CACHE_PER_PX} B/px = {gb(est['decomposition_cache'])}",
             "  (with 2D priors; streamed views, where the build has them, hold neither figure)"]
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------------
# Runs

def _child_env() -> Dict[str, str]:
    """The environment of the launched processes: this checkout first on PYTHONPATH, so that they run the code
    this benchmark runs (an editable install elsewhere would otherwise win)."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def train_command(scene: Path, run: Path, ranks: int, steps: int, device: str, config: str,
                  sets: Sequence[str]) -> List[str]:
    """The command line of one run (N = 1: the plain CLI; N > 1: torch.distributed.run with N processes)."""
    launch = [sys.executable, "-m", "retinexgs"] if ranks == 1 else [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(ranks), "-m",
        "retinexgs"]
    cmd = launch + ["train", "--data", str(scene), "--out", str(run), "--device", device, "--quiet",
                    "--set", f"steps={steps}"]
    if config != "default":
        cmd += ["--config", config]
    for s in sets:
        cmd += ["--set", s]
    return cmd


def run_process(cmd: Sequence[str], log: Path, env: Optional[Dict[str, str]] = None) -> Tuple[int, float, float]:
    """Run ``cmd`` with its output in ``log``: (exit status, wall seconds, the largest RSS of any process of its
    tree in GB, from wait4: the process itself or any child it waited for)."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        p = subprocess.Popen(list(cmd), stdout=f, stderr=subprocess.STDOUT, env=env)
        try:
            _, status, usage = os.wait4(p.pid, 0)
        except BaseException:
            p.terminate()
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
            raise
        p.returncode = os.waitstatus_to_exitcode(status)
    return p.returncode, time.perf_counter() - t0, usage.ru_maxrss * 1024 / GB


def _metrics(run: Path) -> Optional[Dict]:
    try:
        m = json.loads((run / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    return m if isinstance(m, dict) else None


NOTES = {
    "views_fallback": "views/s computed here: steps × views a step / train_seconds (the training does not record "
                      "views_per_second; views a step = ranks × views per rank)",
    "gpu_single": "peak GPU memory: the training's peak_gpu_memory_gb (one process; no per-rank list recorded)",
    "gpu_missing": "peak GPU memory: not recorded (a CPU run, or no peak_gpu_memory_gb_per_rank)",
    "rss_fallback": "host RSS measured here: the largest process of the launched tree (wait4's ru_maxrss); the "
                    "training does not record host_rss_gb_per_rank",
    "first_missing": "time to first step: not recorded by this build's training (train.time_to_first_step)",
    "ranks_missing": "ranks: as launched (the training does not record train.ranks)",
    "quality_missing": "PSNR / SSIM: no test views with a normal-light truth (metrics.json has no mean psnr)",
}


def summarize(ranks: int, metrics: Optional[Dict], wall: Optional[float], rss_gb: Optional[float],
              views_per_rank: int = 1) -> Tuple[Dict, List[str]]:
    """One run's figures from its metrics.json (None: missing) and the notes of the fallbacks used."""
    t = dict((metrics or {}).get("train") or {})
    mean = dict((metrics or {}).get("mean") or {})
    notes: List[str] = []
    row: Dict = {"gpus": ranks, "wall_seconds": None if wall is None else round(wall, 1)}
    row["ranks"] = t.get("ranks")
    if row["ranks"] is None:
        row["ranks"] = ranks
        notes.append("ranks_missing")
    row["views_per_step"] = t.get("views_per_step") or row["ranks"] * views_per_rank
    row["steps"] = t.get("steps")
    row["views_seen"] = None if row["steps"] is None else row["steps"] * row["views_per_step"]
    secs = t.get("train_seconds")
    row["train_seconds"] = secs
    row["views_per_second"] = t.get("views_per_second")
    if row["views_per_second"] is None and secs and row["steps"]:
        row["views_per_second"] = row["views_seen"] / secs
        notes.append("views_fallback")
    row["steps_per_second"] = row["steps"] / secs if secs and row["steps"] else None
    per_rank = t.get("peak_gpu_memory_gb_per_rank")
    if per_rank:
        row["peak_gpu_gb_per_rank"] = [float(x) for x in per_rank]
    elif t.get("peak_gpu_memory_gb") is not None:
        row["peak_gpu_gb_per_rank"] = [float(t["peak_gpu_memory_gb"])]
        notes.append("gpu_single")
    else:
        row["peak_gpu_gb_per_rank"] = None
        notes.append("gpu_missing")
    rss = t.get("host_rss_gb_per_rank")
    if rss:
        row["host_rss_gb_max"] = max(float(x) for x in rss)
        row["host_rss_gb_per_rank"] = [float(x) for x in rss]
    else:
        row["host_rss_gb_max"] = None if rss_gb is None else round(rss_gb, 3)
        notes.append("rss_fallback")
    row["time_to_first_step"] = t.get("time_to_first_step")
    if row["time_to_first_step"] is None:
        notes.append("first_missing")
    row["psnr"], row["ssim"] = mean.get("psnr"), mean.get("ssim")
    # The exposure the EnhancementNet gives the test views moves the plain PSNR by dB between runs; aligned to
    # the truth's grey mean it compares the reconstructions themselves (issue 34: rank counts at equal views seen).
    row["psnr_gt_mean"] = mean.get("psnr_gt_mean")
    if row["psnr"] is None:
        notes.append("quality_missing")
    row["gaussians"] = t.get("gaussians")
    row["device"] = t.get("device")
    for key in STEADY_KEYS:  # the steady rate and the density events' cost (recorded since 2026-11-26)
        row[key] = t.get(key)
    return row, notes


STEADY_KEYS = ("views_per_second_after_first_step", "first_step_seconds", "density_event_steps",
               "density_event_overhead_seconds")
MEANS = ("views_per_second", "steps_per_second", "host_rss_gb_max", "time_to_first_step", "train_seconds",
         "wall_seconds", "gaussians", "psnr", "ssim", "psnr_gt_mean") + STEADY_KEYS


def aggregate(runs: Sequence[Dict]) -> Dict:
    """One rank count's row over its seeds: the first run's keys, the mean of every figure in :data:`MEANS` over
    the runs that finished (``psnr_std``/``ssim_std``/``views_per_second_std``: their sample spread), the
    seeds, and the status "ok" when every run finished (else the first failure's)."""
    runs = list(runs)
    ok = [r for r in runs if r.get("status") == "ok"]
    row = dict(ok[0] if ok else runs[0])
    row["seeds"] = [r.get("seed") for r in ok]
    row["status"] = "ok" if ok and len(ok) == len(runs) else next(
        (r.get("status", "?") for r in runs if r.get("status") != "ok"), "?")
    if ok and len(ok) < len(runs):
        row["status"] = f"ok for {len(ok)} of {len(runs)} seeds; " + row["status"]
    for key in MEANS:
        vals = [float(r[key]) for r in ok if r.get(key) is not None]
        if len(vals) == len(ok) and vals:
            row[key] = sum(vals) / len(vals)
            if key in ("psnr", "ssim", "psnr_gt_mean", "views_per_second") and len(vals) > 1:
                mu = row[key]
                row[f"{key}_std"] = math.sqrt(sum((v - mu) ** 2 for v in vals) / (len(vals) - 1))
    if ok:
        gpus = [r["peak_gpu_gb_per_rank"] for r in ok if r.get("peak_gpu_gb_per_rank")]
        row["peak_gpu_gb_per_rank"] = [max(v) for v in zip(*gpus)] if gpus else None
        row["notes"] = sorted({n for r in ok for n in r.get("notes", ())})
    return row


def _num(v, fmt: str) -> str:
    return "–" if v is None else format(v, fmt)


def table(rows: Sequence[Dict]) -> str:
    """Markdown: one column per rank count, one row per figure; speed-up and efficiency against the 1-rank run.
    A row dict is :func:`summarize`'s with ``status`` ("ok", "failed ..." or "skipped ..."), ``notes`` (keys of
    :data:`NOTES`) and ``planned_steps``."""
    base = next((r for r in rows if r["gpus"] == 1 and r.get("status") == "ok" and r.get("views_per_second")), None)
    marks: Dict[str, str] = {}

    def mark(r: Dict, *keys: str) -> str:
        out = ""
        for k in keys:
            if k in r.get("notes", ()):
                marks.setdefault(k, str(len(marks) + 1))
                out += f" ({marks[k]})"
        return out

    head = "| | " + " | ".join(f"{r['gpus']} {'GPU' if r['gpus'] == 1 else 'GPUs'}" for r in rows) + " |"
    lines = [head, "|---|" + "---|" * len(rows)]

    def add(label: str, fn, always: bool = False) -> None:
        """One row; ``fn`` only for the runs that finished, "–" elsewhere unless ``always``."""
        lines.append(f"| {label} | " + " | ".join(fn(r) if always or r.get("status") == "ok" else "–"
                                                  for r in rows) + " |")

    def speedup(r: Dict, key: str = "views_per_second") -> Optional[float]:
        if base is None or not r.get(key) or not base.get(key):
            return None
        return r[key] / base[key]

    def pm(r: Dict, key: str, fmt: str) -> str:
        std = r.get(f"{key}_std")
        return _num(r.get(key), fmt) + ("" if std is None else f" ± {std:{fmt}}")

    def steady(r: Dict) -> str:
        v = r.get("views_per_second_after_first_step")
        s = speedup(r, "views_per_second_after_first_step")
        return "–" if v is None else f"{v:.2f}" + ("" if s is None else f" ({s:.2f}×, {100 * s / r['gpus']:.0f} %)")

    def events(r: Dict) -> str:
        n, over = r.get("density_event_steps"), r.get("density_event_overhead_seconds")
        return "–" if n is None else f"{n:.0f}; {_num(over, '.2f')} s"

    def gpu(r: Dict) -> str:
        v = r.get("peak_gpu_gb_per_rank")
        if not v:
            return "–" + mark(r, "gpu_missing")
        text = f"{max(v):.2f}" if len(v) == 1 or max(v) - min(v) < 0.005 else f"{max(v):.2f} (min {min(v):.2f})"
        return text + mark(r, "gpu_single")

    add("status", lambda r: r.get("status", "?"), always=True)
    add("ranks × views per rank", lambda r: f"{r['ranks']} × {r['views_per_step'] // max(1, r['ranks'])}"
        + mark(r, "ranks_missing"))
    add("steps (views seen)", lambda r: f"{_num(r['steps'], 'd')} ({_num(r['views_seen'], 'd')})"
        if r.get("status") == "ok" else f"{r.get('planned_steps', '–')} planned", always=True)
    add("seeds", lambda r: ", ".join("config's" if x is None else str(x) for x in r.get("seeds", [r.get("seed")])))
    add("**views/s**", lambda r: pm(r, "views_per_second", ".2f") + mark(r, "views_fallback"))
    add("steps/s", lambda r: _num(r.get("steps_per_second"), ".2f"))
    add("speed-up (views/s over 1 GPU)", lambda r: "–" if speedup(r) is None else f"{speedup(r):.2f}×")
    add("efficiency (speed-up / N)", lambda r: "–" if speedup(r) is None else f"{100 * speedup(r) / r['gpus']:.0f} %")
    add("views/s after step 1 (speed-up, efficiency)", steady)
    add("first step (s)", lambda r: _num(r.get("first_step_seconds"), ".2f"))
    add("density events: steps timed; seconds beyond plain steps", events)
    add("peak GPU memory per rank (GB)", gpu)
    add("host RSS, largest rank (GB)", lambda r: _num(r.get("host_rss_gb_max"), ".2f") + mark(r, "rss_fallback"))
    add("time to first step (s)", lambda r: _num(r.get("time_to_first_step"), ".1f") + mark(r, "first_missing"))
    add("training time (s)", lambda r: _num(r.get("train_seconds"), ".1f"))
    add("wall time of the run (s)", lambda r: _num(r.get("wall_seconds"), ".0f"), always=True)
    add("Gaussians at the end", lambda r: "–" if r.get("gaussians") is None else f"{r['gaussians'] / 1000:.1f}k")
    add("PSNR / SSIM (test views)", lambda r: ("–" if r.get("psnr") is None else
                                               f"{pm(r, 'psnr', '.2f')} / {pm(r, 'ssim', '.3f')}")
        + mark(r, "quality_missing"))
    add("PSNR aligned to the truth's grey mean (GT-mean)", lambda r: pm(r, "psnr_gt_mean", ".2f"))
    text = "\n".join(lines) + ("\n\nviews/s and steps/s over the training time (train_seconds: the steps alone); "
                                "speed-up: views/s over the 1-GPU run's; efficiency: speed-up / N; after step 1: "
                                "the first step (warm-up, graph captures; also in the time to first step) left out; "
                                "density events: each event's step and the next (its re-captures) timed between "
                                "syncs, less as many plain steps' time (the same events at any rank count); several "
                                "seeds: means (± sample std); wall time: the whole process (start, loading the "
                                "views, training, evaluation); GB = 2^30 bytes.")
    if marks:
        text += "\n\n" + "\n".join(f"({n}) {NOTES[k]}" for k, n in marks.items())
    return text + "\n"


# ----------------------------------------------------------------------------------------------------
# Main

def _resolve_device(device: str) -> str:
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device not in ("cuda", "cpu"):
        raise UserError(f"--device {device!r}: cuda, cpu or auto")
    if device == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda: no CUDA device here")
    return device


def _print_progress(done: int, total: int, seconds: float) -> None:
    if done == total or done % max(1, math.ceil(total / 10)) == 0:
        print(f"  generated {done}/{total} views in {seconds:.1f} s ({done / max(seconds, 1e-9):.1f} views/s)",
              flush=True)


def _generate(folder: str, params: Dict) -> None:
    """Generation in a process of its own (for the GPU: its CUDA context and cached memory go when it ends)."""
    torch.set_num_threads(max(1, min(8, os.cpu_count() or 1)))
    ensure_large_scene(Path(folder), params, progress=_print_progress)


def make_scene(args: argparse.Namespace, device: str, separate_process: Optional[bool] = None) -> Tuple[Path, Dict]:
    """The scene to train: --scene as it is, or the generated one (made here or reused). Returns (folder, info).
    ``separate_process`` (default: on the GPU) generates it in a spawned process, so that this one holds no CUDA
    context or cached GPU memory while the trainings run."""
    if args.scene is not None:
        if not args.scene.is_dir():
            raise UserError(f"--scene {args.scene}: not a folder")
        return args.scene, {"path": str(args.scene), "generated": False}
    params = scene_params(args.views, args.test_views, args.width, args.height, args.seed, args.format,
                          args.supersample, args.points, device)
    folder = args.scenes_dir / default_folder_name(params)
    recorded = folder / PARAMS_FILE
    reused = recorded.is_file() and json.loads(recorded.read_text()).get("params") == params
    if reused:
        print(f"scene: reusing {folder} (same parameters)", flush=True)
    else:
        print(f"scene: generating {args.views} + {args.test_views} test views at {args.width}x{args.height} "
              f"({args.format}) on {device} into {folder}", flush=True)
        if device == "cuda" if separate_process is None else separate_process:
            ctx = multiprocessing.get_context("spawn")
            p = ctx.Process(target=_generate, args=(str(folder), params))
            p.start()
            p.join()
            if p.exitcode != 0:
                raise UserError(f"the scene's generation failed (exit {p.exitcode}); see the output above")
        else:
            ensure_large_scene(folder, params, progress=_print_progress)
    recorded_all = json.loads(recorded.read_text())
    gen = recorded_all.get("generation", {})
    if not reused:
        print(f"scene: {gen.get('views')} views in {gen.get('seconds')} s = {gen.get('views_per_second')} views/s "
              f"on {gen.get('device')}, {gen.get('bytes', 0) / 2**20:.0f} MiB of images", flush=True)
    return folder, {"path": str(folder), "generated": True, "reused": reused, "params": params, "generation": gen}


def _disk_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for sub in ("low", "high") if (folder / sub).is_dir()
               for p in (folder / sub).iterdir() if p.is_file())


# Passes over the training views under which the PSNR at equal views seen favours one view a step.
SHORT_RUN_PASSES = 20


def write_report(out: Path, header: str, rows: List[Dict], report: Dict, estimate_text: str) -> str:
    md = header + "\n\n" + table(rows) + "\n```\n" + estimate_text + "\n```\n"
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "scale.md", md)
    atomic_write_text(out / "scale.json", json.dumps(dict(report, runs=rows), indent=2) + "\n")
    return md


def _row_file(run: Path) -> Path:
    return run.parent / f"{run.name}.row.json"


def finished_row(run: Path, cmd: Sequence[str]) -> Optional[Dict]:
    """The row of a run an earlier call finished with the same command line (``--reuse``), or None."""
    try:
        saved = json.loads(_row_file(run).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(saved, dict) or saved.get("command") != list(cmd[1:]) or _metrics(run) is None:
        return None
    row = saved.get("row")
    return row if isinstance(row, dict) and row.get("status") == "ok" else None


def main(argv: Sequence[str]) -> int:
    ap = argparse.ArgumentParser(prog="python -m retinexgs.bench scale", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--scene", type=Path, default=None, help="train this scene folder instead of a generated one")
    ap.add_argument("--views", type=int, default=1000, help="generated scene: training views")
    ap.add_argument("--test-views", type=int, default=8, help="generated scene: test views (with normal-light truth)")
    ap.add_argument("--width", type=int, default=1920, help="generated scene: image width")
    ap.add_argument("--height", type=int, default=1080, help="generated scene: image height")
    ap.add_argument("--format", choices=FORMATS, default="jpg", help="generated scene: image files")
    ap.add_argument("--seed", type=int, default=0, help="generated scene: cameras and noise")
    ap.add_argument("--supersample", type=int, default=2, help="generated scene: rays per pixel side")
    ap.add_argument("--points", type=int, default=20000, help="generated scene: initial surface points")
    ap.add_argument("--scenes-dir", type=Path, default=Path(tempfile.gettempdir()) / "retinexgs-scale",
                    help="where generated scenes are kept (one folder per parameter set, reused)")
    ap.add_argument("--gpus", default="1,2,4", help="rank counts to train, e.g. 1,2,4 (on the CPU: gloo processes)")
    ap.add_argument("--seeds", default=None, help="training seeds, e.g. 0,1,2: every rank count trains once per seed "
                    "(seed by seed; passed as --set seed=S); the table gives means (± std). Default: the config's")
    ap.add_argument("--views-seen", type=int, default=2000,
                    help="views every run sees: steps = ceil(V / (N x views per rank))")
    ap.add_argument("--views-per-rank", type=int, default=None,
                    help="views each rank renders a step (passed as train.views_per_rank; default: the config's, 1)")
    ap.add_argument("--config", default="default", help="config name in configs/ (default: configs/default.yaml)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override for every run")
    ap.add_argument("--decompose", choices=("once", "none"), default="once",
                    help="once: `retinexgs decompose` before the trainings (cached, untimed); none: no 2D priors")
    ap.add_argument("--stream-views", choices=("auto", "always", "never"), default=None,
                    help="passed as train.stream_views (builds that stream views)")
    ap.add_argument("--views-on-device-gb", type=float, default=None, help="passed as train.views_on_device_gb")
    ap.add_argument("--device", default="auto", help="cuda, cpu or auto (scene generation, decomposition, training)")
    ap.add_argument("--out", type=Path, default=Path("runs/scale"), help="scale.md, scale.json and the runs")
    ap.add_argument("--generate-only", action="store_true", help="make (or reuse) the scene, print the estimate, stop")
    ap.add_argument("--reuse", action="store_true",
                    help="keep a run that an earlier call with the same --out finished with the same command (its row "
                         "is read back, not trained again): add seeds or rank counts to one table over several calls")
    args = ap.parse_args(list(argv))
    try:
        gpus = parse_gpus(args.gpus)
        try:
            seeds: List[Optional[int]] = [None] if args.seeds is None else list(dict.fromkeys(
                int(x) for x in args.seeds.replace(" ", ",").split(",") if x.strip()))
        except ValueError:
            raise ValueError(f"--seeds {args.seeds!r}: a comma-separated list of integers, e.g. 0,1,2") from None
        if not seeds or (args.seeds is not None and min(seeds) < 0):
            raise ValueError(f"--seeds {args.seeds!r}: one or more integers >= 0")
        if args.views_seen < 1 or (args.views_per_rank is not None and args.views_per_rank < 1):
            raise ValueError("--views-seen and --views-per-rank must be >= 1")
        if args.scene is None and (args.views < 1 or args.test_views < 0 or args.width < 2 or args.height < 2):
            raise ValueError("--views >= 1, --test-views >= 0, --width and --height >= 2")
        device = _resolve_device(args.device)
    except (ValueError, UserError) as exc:
        print(f"python -m retinexgs.bench scale: error: {exc}", file=sys.stderr)
        return 2
    try:
        return _run(args, gpus, device, seeds)
    except UserError as exc:
        print(f"python -m retinexgs.bench scale: error: {exc}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace, gpus: List[int], device: str, seeds: Sequence[Optional[int]] = (None,)) -> int:
    t0 = time.perf_counter()
    scene, scene_info = make_scene(args, device)
    views, width, height = scene_size(scene)
    scene_info.update(train_views=views, width=width, height=height, image_bytes=_disk_bytes(scene))
    est = estimate(views, width, height, _gpu_total_bytes() if device == "cuda" else None, _host_total_bytes())
    est_text = format_estimate(est)
    print(est_text, flush=True)
    if args.generate_only:
        return 0

    sets = list(args.set)
    if args.views_per_rank is not None:
        sets.append(f"train.views_per_rank={args.views_per_rank}")
    if args.stream_views is not None:
        sets.append(f"train.stream_views={args.stream_views}")
    if args.views_on_device_gb is not None:
        sets.append(f"train.views_on_device_gb={args.views_on_device_gb}")
    no_priors = args.decompose == "none" or any(s.replace(" ", "") == "decomposer.method=none" for s in sets)
    if args.decompose == "none" and "decomposer.method=none" not in sets:
        sets.append("decomposer.method=none")
    env = _child_env()
    args.out.mkdir(parents=True, exist_ok=True)
    report: Dict = {"scene": scene_info, "estimate": est, "config": args.config, "sets": sets,
                    "views_seen": args.views_seen, "device": device, "decompose": {"mode": "none" if no_priors
                                                                                   else "once"}}
    if not no_priors:
        cmd = [sys.executable, "-m", "retinexgs", "decompose", "--data", str(scene), "--device", device, "--quiet"]
        if args.config != "default":
            cmd += ["--config", args.config]
        for s in sets:
            cmd += ["--set", s]
        print("decomposition (once, not timed in the trainings): " + " ".join(cmd[1:]), flush=True)
        rc, wall, _ = run_process(cmd, args.out / "decompose.log", env)
        report["decompose"].update(seconds=round(wall, 1), exit=rc)
        if rc != 0 and "there is nothing to decompose" in (args.out / "decompose.log").read_text():
            print("  the config has no decomposer (decomposer.method: none): trained without priors", flush=True)
            report["decompose"]["mode"] = "none (the config's)"
            no_priors = True
        elif rc != 0:
            print(f"the decomposition failed (exit {rc}); see {args.out / 'decompose.log'}:", file=sys.stderr)
            print("".join((args.out / "decompose.log").read_text().splitlines(True)[-10:]), file=sys.stderr)
            return 1
        else:
            done = (args.out / "decompose.log").read_text().strip().splitlines()
            print(f"  {wall:.0f} s: " + " ".join(done[-2:]), flush=True)

    vpr = args.views_per_rank or 1
    gpu_count = torch.cuda.device_count() if device == "cuda" else None
    distributed = has_distributed()
    header = (f"## Scale: {scene} ({views} training views at {width}x{height}), config `{args.config}`"
              + (f" + {', '.join(f'`{s}`' for s in sets)}" if sets else "")
              + f", {args.views_seen} views seen per run ({args.views_seen / max(views, 1):.1f} passes over the "
              f"training views), device {device}"
              + ("" if no_priors else ", decomposition done once beforehand"))
    if len(gpus) > 1 and args.views_seen < SHORT_RUN_PASSES * views:
        # What the PSNR column can say: measured on one H100 (experiments/notes/2026-11-27-batch-views-seen.md).
        header += (f"\n\nA short run (under {SHORT_RUN_PASSES} passes): at equal views seen a batch of several views "
                   "makes fewer optimiser steps, and in a short run it trails one view a step (a batch of 4: −0.37 dB "
                   "at 8 passes on 4 H100s, and +0.44 dB at 20, GT-mean −0.15 dB; −0.76 dB at 10 passes and +0.66 dB "
                   "at 40 on one). Compare PSNR with more --views-seen.")
    runs: Dict[int, List[Dict]] = {n: [] for n in gpus}
    failed = False

    def rows_now() -> List[Dict]:
        return [aggregate(runs[n]) if runs[n] else {"gpus": n, "planned_steps": steps_for(args.views_seen, n, vpr),
                                                    "status": "not run"} for n in gpus]

    for seed, n in [(s, n) for s in seeds for n in gpus]:
        steps = steps_for(args.views_seen, n, vpr)
        row: Dict = {"gpus": n, "planned_steps": steps, "seed": seed}
        rows = runs[n]
        if gpu_count is not None and n > gpu_count:
            row["status"] = f"skipped: {gpu_count} GPU(s) here"
        elif n > 1 and not distributed:
            row["status"] = "skipped: no retinexgs.train.distributed in this build"
        if "status" in row:
            print(f"{n} rank(s): {row['status']}", flush=True)
            rows.append(row)
            write_report(args.out, header, rows_now(), report, est_text)
            continue
        name = f"gpus{n}" + ("" if seed is None else f"-seed{seed}")
        run = args.out / "runs" / name
        cmd = train_command(scene, run, n, steps, device, args.config, sets + ([] if seed is None else [f"seed={seed}"]))
        kept = finished_row(run, cmd) if args.reuse else None
        if kept is not None:
            print(f"{n} rank(s), seed {'as configured' if seed is None else seed}: reused the finished run {run}",
                  flush=True)
            rows.append(kept)
            write_report(args.out, header, rows_now(), report, est_text)
            continue
        _row_file(run).unlink(missing_ok=True)  # a row stands only for the run trained beside it
        if run.exists():
            shutil.rmtree(run)
        run.parent.mkdir(parents=True, exist_ok=True)
        print(f"{n} rank(s), seed {'as configured' if seed is None else seed}, {steps} steps: {' '.join(cmd[1:])}", flush=True)
        rc, wall, rss = run_process(cmd, run.parent / f"{name}.log", env)
        m = _metrics(run)
        summary, notes = summarize(n, m, wall, rss, vpr)
        row.update(summary, notes=notes, command=cmd[1:])
        if rc == 0 and m is not None:
            row["status"] = "ok"
        else:
            failed = True
            row["status"] = f"failed (exit {rc}, {run.parent / f'{name}.log'})"
            tail = (run.parent / f"{name}.log").read_text(errors="replace").splitlines()[-15:]
            print("\n".join(f"    | {line}" for line in tail), file=sys.stderr, flush=True)
        rows.append(row)
        if row["status"] == "ok":
            atomic_write_text(_row_file(run), json.dumps({"command": list(cmd[1:]), "row": row}, indent=1))
        vps = row.get("views_per_second")
        print(f"  {row['status']} in {wall:.0f} s" + (f": {vps:.2f} views/s" if vps else "") +
              (f", PSNR {row['psnr']:.2f}" if row.get("psnr") is not None else ""), flush=True)
        write_report(args.out, header, rows_now(), report, est_text)
    report["total_seconds"] = round(time.perf_counter() - t0, 1)
    report["seed_runs"] = [r for n in gpus for r in runs[n]]
    md = write_report(args.out, header, rows_now(), report, est_text)
    print(md)
    print(f"table: {args.out / 'scale.md'}, figures: {args.out / 'scale.json'}")
    return 1 if failed else 0
