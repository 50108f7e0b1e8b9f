"""The 12-megapixel raw night scene end to end (issue 65): darken --raw, then trainings of the raw files with the
decode, denoise and LR3M priors inside each timed training; darken s, time to first step, steps/s, peak GPU memory,
host RSS and PSNR / SSIM, one row per config.

    python -m retinexgs.bench bigraw [--views 40 --test-views 4 --width 4000 --height 3000 | --scene DIR]
        [--configs "SPEC|SPEC|..."] [--steps N] [--set KEY=VALUE ...] [--jobs N] [--limit S]
        [--device auto|cuda|cpu] [--scenes-dir DIR] [--out DIR] [--fresh] [--generate-only]

1. The scene: ``--scene DIR`` (a normal-light scene in LOM layout: high/ photos and transforms JSON) or the
   synthetic demo scene of ``python -m retinexgs.bench scale`` at --views x --width x --height, generated once and
   reused (not timed).
2. ``retinexgs darken --raw --data SCENE --out OUT/dark --jobs N`` (timed): OUT/dark/raw holds the DNGs. Done once
   per call and reused by a later call on the same scene and jobs (``OUT/dark.json`` records it; --fresh redoes it).
3. Every row of ``--configs`` trains OUT/dark/raw in turn with ``python -m retinexgs train``, each from cold caches
   (``data.cache_dir`` = OUT/caches/RUN, emptied first and removed after), so that the raw decode, the denoising and
   the LR3M priors happen inside the training, as a user's first run does: the training's ``time_to_first_step``
   (from the process's start to the end of step 1) holds them. A row SPEC is whitespace-separated tokens: at most
   one config name (no ``=``; default ``default``) and KEY=VALUE overrides, e.g.
   ``--configs "default|train.resolution=[[0.8,4],[0.95,2]]|data.downscale=2"`` (the last: the same views at half
   size, for the PSNR comparison). ``--steps N`` sets every row's steps but a row's own ``steps=``.

``--limit S`` stops the whole benchmark S seconds after it began: a training still running then gets SIGINT (it
writes its checkpoint), then SIGKILL after a grace; its row reads "cut off" with steps/s from its train_log.jsonl,
and later rows "not run". A row that an earlier call finished with the same command is read back, not trained
again (--fresh trains it again), so a cut-off table is completed by running the same command once more.
Writes ``OUT/bigraw.md`` and ``OUT/bigraw.json`` atomically after the darkening and after every row.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

from retinexgs.bench.scale import GB, _child_env, _metrics, _resolve_device, make_scene, scene_size
from retinexgs.demo.large import FORMATS
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write_text

PROG = "python -m retinexgs.bench bigraw"
GRACE_SECONDS = 30  # after SIGINT, time for the training to write its checkpoint and exit before SIGKILL
DARK_RECORD = "dark.json"


# ----------------------------------------------------------------------------------------------------
# Rows

def parse_configs(text: str) -> List[Dict]:
    """``"default|train.resolution=[[0.8,4],[0.95,2]]|ablations/x steps=3000"`` -> one dict a row: ``label`` (the
    spec as written), ``config`` (the one token without ``=``; default ``default``), ``sets`` (KEY=VALUE tokens).
    ValueError (one line) on an empty row, two config names or an override without a key."""
    rows = []
    for spec in text.split("|"):
        tokens = spec.split()
        if not tokens:
            raise ValueError(f"--configs {text!r}: an empty row (rows are separated by |)")
        names = [t for t in tokens if "=" not in t]
        if len(names) > 1:
            raise ValueError(f"--configs row {spec.strip()!r}: two config names ({names[0]}, {names[1]}); "
                             "a row is one config name and KEY=VALUE overrides")
        sets = [t for t in tokens if "=" in t]
        bad = next((s for s in sets if not s.split("=", 1)[0]), None)
        if bad is not None:
            raise ValueError(f"--configs row {spec.strip()!r}: {bad!r} has no key (KEY=VALUE)")
        rows.append({"label": " ".join(tokens), "config": names[0] if names else "default", "sets": sets})
    labels = [r["label"] for r in rows]
    if len(set(labels)) < len(labels):
        raise ValueError(f"--configs {text!r}: a row is listed twice")
    return rows


def run_name(index: int, label: str) -> str:
    """A run folder's name: its position and the spec's letters (``2-train.resolution-0.8-4-0.95-2``)."""
    safe = "".join(c if c.isalnum() or c in "._" else "-" for c in label)
    return f"{index}-" + "-".join(p for p in safe.split("-") if p)[:60]


def train_command(data: Path, run: Path, cache: Path, device: str, row: Dict, steps: Optional[int],
                  sets: Sequence[str], gpu_memory_gb: Optional[float] = None) -> List[str]:
    """The training of one row: its caches in ``cache`` (emptied before it runs: cold), --steps unless the row
    sets its own; under ``gpu_memory_gb`` (:mod:`retinexgs.bench.capped`) where given."""
    launch = ["retinexgs"] if gpu_memory_gb is None else ["retinexgs.bench.capped", f"{gpu_memory_gb:g}"]
    cmd = [sys.executable, "-m", *launch, "train", "--data", str(data), "--out", str(run), "--device", device,
           "--quiet", "--set", f"data.cache_dir={cache}"]
    if row["config"] != "default":
        cmd += ["--config", row["config"]]
    own = list(sets) + list(row["sets"])
    if steps is not None and not any(s.split("=", 1)[0].strip() == "steps" for s in own):
        cmd += ["--set", f"steps={steps}"]
    for s in own:
        cmd += ["--set", s]
    return cmd


def run_until(cmd: Sequence[str], log: Path, deadline: Optional[float],
              env: Optional[Dict[str, str]] = None) -> Tuple[int, float, float, bool]:
    """Run ``cmd`` (output in ``log``) until it ends or ``deadline`` (time.monotonic()): (exit status, wall
    seconds, the largest RSS of its process tree in GB from wait4, cut off). At the deadline it gets SIGINT (a
    training writes its checkpoint), then SIGKILL after :data:`GRACE_SECONDS`. Each line of the log starts with
    the seconds since the start at which it was written (where a run's set-up spends its time); of a progress
    bar's redraws (``\\r``) only the last before a newline is kept."""
    t0 = time.monotonic()
    cut = False
    with open(log, "w") as f:
        p = subprocess.Popen(list(cmd), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
        reader = threading.Thread(target=_stamp_lines, args=(p.stdout, f, t0), daemon=True)
        reader.start()
        try:
            while True:
                pid, status, usage = os.wait4(p.pid, os.WNOHANG)
                if pid:
                    break
                now = time.monotonic()
                if deadline is not None and now >= deadline and not cut:
                    cut = True
                    p.send_signal(signal.SIGINT)
                    deadline = now + GRACE_SECONDS
                elif cut and deadline is not None and now >= deadline:
                    p.kill()
                    deadline = None
                time.sleep(0.2)
        except BaseException:
            p.kill()
            p.wait()
            raise
        finally:
            reader.join(timeout=5)  # a grandchild may hold the pipe open: the log is complete enough then
        p.returncode = os.waitstatus_to_exitcode(status)
    return p.returncode, time.monotonic() - t0, usage.ru_maxrss * 1024 / GB, cut


def _stamp_lines(stream, out, t0: float) -> None:
    """Copy ``stream`` (bytes) to the text file ``out`` line by line, each line prefixed with ``[  12.3 s]``."""
    pending = b""
    for chunk in iter(lambda: stream.read1(65536), b""):
        pending += chunk
        *lines, pending = pending.split(b"\n")
        for line in lines:
            _stamp(out, line, t0)
        out.flush()
    if pending:
        _stamp(out, pending, t0)
        out.flush()


def _stamp(out, line: bytes, t0: float) -> None:
    redraws = [part for part in line.split(b"\r") if part.strip()]  # a progress bar's last redraw
    text = redraws[-1].decode(errors="replace").rstrip() if redraws else ""
    out.write(f"[{time.monotonic() - t0:7.1f} s] {text}\n")


def _progress(run: Path) -> Tuple[Optional[int], Optional[float]]:
    """(steps, seconds) of the last timed line of a run's train_log.jsonl (a cut-off run's steps/s)."""
    steps = secs = None
    try:
        lines = (run / "train_log.jsonl").read_text().splitlines()
    except OSError:
        return None, None
    for line in lines:
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if isinstance(rec, dict) and "seconds" in rec and "step" in rec:
            steps, secs = int(rec["step"]), float(rec["seconds"])
    return steps, secs


def summarize(metrics: Optional[Dict], wall: float, rss_gb: float, darken_seconds: Optional[float]) -> Dict:
    """One row's figures from its metrics.json (None where missing; host RSS from wait4 where not recorded)."""
    t = dict((metrics or {}).get("train") or {})
    mean = dict((metrics or {}).get("mean") or {})
    row: Dict = {"steps": t.get("steps"), "train_seconds": t.get("train_seconds"),
                 "time_to_first_step": t.get("time_to_first_step"), "wall_seconds": round(wall, 1),
                 "views_set_up_seconds": t.get("views_set_up_seconds"),
                 "peak_gpu_allocated_gb": t.get("peak_gpu_memory_gb"),
                 "peak_gpu_reserved_gb": t.get("peak_gpu_memory_reserved_gb"),
                 "gaussians": t.get("gaussians"), "psnr": mean.get("psnr"), "ssim": mean.get("ssim"),
                 "psnr_gt_mean": mean.get("psnr_gt_mean"), "ssim_gt_mean": mean.get("ssim_gt_mean")}
    rss = t.get("host_rss_gb_per_rank")
    row["host_rss_gb"] = max(float(x) for x in rss) if rss else round(rss_gb, 3)
    row["host_rss_measured_here"] = not rss
    row["steps_per_second"] = (row["steps"] / row["train_seconds"]
                               if row["steps"] and row["train_seconds"] else None)
    row["total_seconds"] = None if darken_seconds is None else round(darken_seconds + wall, 1)
    return row


def _num(v, fmt: str) -> str:
    return "–" if v is None else format(v, fmt)


COLUMNS = (("config", lambda r: f"`{r['label']}`"), ("status", lambda r: r.get("status", "?")),
           ("steps", lambda r: _num(r.get("steps"), "d") if r.get("steps") is not None
            else f"{r.get('planned_steps') or 'config'} planned"),
           ("time to first step (s)", lambda r: _num(r.get("time_to_first_step"), ".1f")
            + (f" (views {r['views_set_up_seconds']:.1f})" if r.get("views_set_up_seconds") is not None else "")),
           ("steps/s", lambda r: _num(r.get("steps_per_second"), ".2f")),
           ("training (s)", lambda r: _num(r.get("train_seconds"), ".1f")),
           ("run wall (s)", lambda r: _num(r.get("wall_seconds"), ".0f")),
           ("darken + run (s)", lambda r: _num(r.get("total_seconds"), ".0f")),
           ("peak GPU allocated / reserved (GB)", lambda r: f"{_num(r.get('peak_gpu_allocated_gb'), '.2f')} / "
            f"{_num(r.get('peak_gpu_reserved_gb'), '.2f')}"),
           ("host RSS (GB)", lambda r: _num(r.get("host_rss_gb"), ".2f") + (" (w)" if r.get("host_rss_measured_here")
                                                                             else "")),
           ("Gaussians", lambda r: "–" if r.get("gaussians") is None else f"{r['gaussians'] / 1000:.1f}k"),
           ("PSNR / SSIM", lambda r: f"{_num(r.get('psnr'), '.2f')} / {_num(r.get('ssim'), '.3f')}"),
           ("GT-mean PSNR / SSIM", lambda r: f"{_num(r.get('psnr_gt_mean'), '.2f')} / "
            f"{_num(r.get('ssim_gt_mean'), '.3f')}"))


def table(rows: Sequence[Dict]) -> str:
    """Markdown, one line per row of ``--configs``."""
    lines = ["| " + " | ".join(c for c, _ in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(fn(r) for _, fn in COLUMNS) + " |" for r in rows]
    return "\n".join(lines) + (
        "\n\ntime to first step: from the training process's start to the end of step 1 (imports, raw decode, "
        "denoising, LR3M priors, set-up; cold caches), in brackets the views' set-up alone (photos, priors, view "
        "store); steps/s: steps / training time (the steps alone); run wall: "
        "the whole training process (evaluation included); darken + run: the darkening's wall time plus the run's "
        "(end to end as a user, the scene's generation not counted); peak GPU: torch's max allocated / reserved "
        "(– on the CPU, or where the training does not record it); (w): host RSS measured here (wait4), not "
        "recorded by the training; a cut-off row's steps/s from its train_log.jsonl; GB = 2^30 bytes.\n")


def write_report(out: Path, report: Dict, rows: List[Dict]) -> str:
    d = report.get("darken") or {}
    head = (f"## 12 MP raw night scene (issue 65): {report['scene']['path']} "
            f"({report['scene'].get('train_views')} training views at {report['scene'].get('width')}x"
            f"{report['scene'].get('height')}), device {report['device']}"
            + (f", each training capped at {report['gpu_memory_gb']:g} GB of GPU memory" if report.get("gpu_memory_gb")
               else "")
            + ("; the rows trained side by side on it: their times are not a training's alone" if
               report.get("side_by_side") else "") + "\n\n"
            f"darken --raw: {_num(d.get('seconds'), '.1f')} s with {d.get('jobs')} jobs"
            + (" (reused from an earlier call)" if d.get("reused") else "") + "\n")
    md = head + "\n" + table(rows)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "bigraw.md", md)
    atomic_write_text(out / "bigraw.json", json.dumps(dict(report, rows=rows), indent=2) + "\n")
    return md


# ----------------------------------------------------------------------------------------------------
# Darkening

def darken(scene: Path, out: Path, jobs: int, deadline: Optional[float], env: Dict[str, str],
           fresh: bool) -> Dict:
    """OUT/dark from ``scene`` by ``darken --raw`` (timed), or the one an earlier call made of the same scene with
    the same jobs (its record in OUT/dark.json). A folder OUT/dark this benchmark did not record is refused."""
    dark, record = out / "dark", out / DARK_RECORD
    key = {"scene": str(scene.resolve()), "jobs": jobs,
           "params": _read_json(scene / "scene_params.json")}
    old = _read_json(record)
    if not fresh and isinstance(old, dict) and old.get("key") == key and (dark / "raw").is_dir():
        print(f"darken: reusing {dark} ({old.get('seconds')} s when it was made)", flush=True)
        return dict(old, reused=True)
    if dark.exists():
        if not isinstance(old, dict):
            raise UserError(f"{dark} exists and this benchmark did not make it (no {record}): choose another --out")
        shutil.rmtree(dark)  # this benchmark's own darkening of other parameters
    record.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "retinexgs", "darken", "--raw", "--data", str(scene), "--out", str(dark),
           "--jobs", str(jobs), "--quiet"]
    print("darken: " + " ".join(cmd[1:]), flush=True)
    rc, wall, _, cut = run_until(cmd, out / "darken.log", deadline, env)
    if rc != 0 or cut:
        tail = (out / "darken.log").read_text(errors="replace").splitlines()[-5:]
        print("\n".join(f"    | {line}" for line in tail), file=sys.stderr)
        raise UserError(f"darken --raw {'was cut off at --limit' if cut else f'failed (exit {rc})'}; "
                        f"see {out / 'darken.log'}")
    done = {"key": key, "seconds": round(wall, 1), "jobs": jobs, "command": cmd[1:], "made": time.time()}
    atomic_write_text(record, json.dumps(done, indent=1))
    print(f"darken: {wall:.1f} s with {jobs} jobs", flush=True)
    return dict(done, reused=False)


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


# ----------------------------------------------------------------------------------------------------
# Main

def main(argv: Sequence[str]) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--scene", type=Path, default=None, help="a normal-light scene (high/ photos) instead of the "
                    "generated one")
    ap.add_argument("--views", type=int, default=40, help="generated scene: training views")
    ap.add_argument("--test-views", type=int, default=4, help="generated scene: test views")
    ap.add_argument("--width", type=int, default=4000, help="generated scene: image width")
    ap.add_argument("--height", type=int, default=3000, help="generated scene: image height")
    ap.add_argument("--format", choices=FORMATS, default="jpg", help="generated scene: image files")
    ap.add_argument("--seed", type=int, default=0, help="generated scene: cameras and noise")
    ap.add_argument("--supersample", type=int, default=2, help="generated scene: rays per pixel side")
    ap.add_argument("--points", type=int, default=20000, help="generated scene: initial surface points")
    ap.add_argument("--scenes-dir", type=Path, default=Path(tempfile.gettempdir()) / "retinexgs-scale",
                    help="where generated scenes are kept (shared with bench scale, reused)")
    ap.add_argument("--configs", default="default",
                    help="rows separated by |, each a config name and/or KEY=VALUE overrides separated by spaces")
    ap.add_argument("--steps", type=int, default=None, help="every row's steps (but a row's own steps=)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override for every row")
    ap.add_argument("--jobs", type=int, default=None, help="darken --raw's workers (default: one per CPU core)")
    ap.add_argument("--limit", type=float, default=None,
                    help="seconds from the start after which the running training is stopped (SIGINT) and the rest "
                         "not run; the tables keep what finished")
    ap.add_argument("--device", default="auto", help="cuda, cpu or auto (generation and trainings)")
    ap.add_argument("--side-by-side", action="store_true",
                    help="train every row at once on the one device (a PSNR comparison that one after another would "
                         "not fit the time; the times are then shared, not a training's alone)")
    ap.add_argument("--gpu-memory-gb", type=float, default=None,
                    help="cap each training's GPU memory at this many GB (2^30), as a smaller card (24: a 4090)")
    ap.add_argument("--out", type=Path, default=Path("runs/bigraw"), help="bigraw.md, bigraw.json, dark/, runs/")
    ap.add_argument("--fresh", action="store_true", help="darken and train again what an earlier call finished")
    ap.add_argument("--generate-only", action="store_true",
                    help="make (or reuse) the scene and stop (scripts/device.sh: while the extension builds)")
    args = ap.parse_args(list(argv))
    try:
        rows = parse_configs(args.configs)
        if args.steps is not None and args.steps < 1:
            raise ValueError(f"--steps {args.steps}: must be >= 1")
        if args.jobs is not None and args.jobs < 1:
            raise ValueError(f"--jobs {args.jobs}: must be >= 1")
        if args.gpu_memory_gb is not None and args.gpu_memory_gb <= 0:
            raise ValueError(f"--gpu-memory-gb {args.gpu_memory_gb:g}: must be > 0")
        if args.limit is not None and args.limit <= 0:
            raise ValueError(f"--limit {args.limit:g}: must be > 0 seconds")
        if args.scene is None and (args.views < 1 or args.test_views < 1 or args.width < 2 or args.height < 2):
            raise ValueError("--views >= 1, --test-views >= 1 (the PSNR needs them), --width and --height >= 2")
        bad = next((s for s in args.set if "=" not in s or not s.split("=", 1)[0]), None)
        if bad is not None:
            raise ValueError(f"--set {bad!r}: KEY=VALUE")
        device = _resolve_device(args.device)
        return _run(args, rows, device)
    except (ValueError, UserError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace, rows: List[Dict], device: str) -> int:
    t0 = time.monotonic()
    deadline = None if args.limit is None else t0 + args.limit
    scene, scene_info = make_scene(args, device)
    if not (scene / "high").is_dir():
        raise UserError(f"{scene}: no high/ folder (darken --raw needs a normal-light scene in LOM layout)")
    views, width, height = scene_size(scene)
    scene_info.update(train_views=views, width=width, height=height)
    if args.generate_only:
        print(f"scene: {scene} ({views} training views at {width}x{height})", flush=True)
        return 0
    env = _child_env()
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = args.jobs or os.cpu_count() or 1
    report: Dict = {"scene": scene_info, "device": device, "configs": args.configs, "sets": list(args.set),
                    "steps": args.steps, "limit": args.limit, "gpu_memory_gb": args.gpu_memory_gb,
                    "side_by_side": bool(args.side_by_side and len(rows) > 1), "darken": None}
    table_rows: List[Dict] = [dict(label=r["label"], status="not run") for r in rows]
    write_report(args.out, report, table_rows)
    report["darken"] = darken(scene, args.out, jobs, deadline, env, args.fresh)
    darken_s = report["darken"]["seconds"]
    data = args.out / "dark" / "raw"
    write_report(args.out, report, table_rows)
    lock = threading.Lock()  # rows side by side write the report one at a time

    def run_row(i: int, spec: Dict) -> bool:
        """Train row ``i`` (or reuse its finished run); its entry of ``table_rows``; False where it failed."""
        name = run_name(i + 1, spec["label"])
        run = args.out / "runs" / name
        cache = args.out / "caches" / name  # not inside the run folder: train wants that one empty
        cmd = train_command(data, run, cache, device, spec, args.steps, args.set, args.gpu_memory_gb)
        row: Dict = {"label": spec["label"], "run": str(run), "command": shlex.join(cmd[1:]),
                     "dark_made": report["darken"].get("made"),  # a row stands only for the DNGs it trained on
                     "planned_steps": next((int(s.split("=", 1)[1]) for s in reversed(cmd) if s.startswith("steps=")
                                            and s.split("=", 1)[1].isdigit()), None)}
        saved = _read_json(run.parent / f"{name}.row.json")
        if (not args.fresh and isinstance(saved, dict) and saved.get("command") == row["command"]
                and saved.get("dark_made") == row["dark_made"] and saved.get("status") == "ok"
                and _metrics(run) is not None):
            print(f"row {i + 1} `{spec['label']}`: reused the finished run {run}", flush=True)
            with lock:
                table_rows[i] = dict(saved, total_seconds=None if saved.get("wall_seconds") is None
                                     else round(darken_s + saved["wall_seconds"], 1))
                write_report(args.out, report, table_rows)
            return True
        if deadline is not None and time.monotonic() >= deadline:
            table_rows[i] = dict(row, status=f"not run: --limit {args.limit:g} s reached")
            return True
        (run.parent / f"{name}.row.json").unlink(missing_ok=True)
        for made in (run, cache):  # this benchmark's own run and caches of an earlier call
            if made.exists():
                shutil.rmtree(made)
        run.parent.mkdir(parents=True, exist_ok=True)
        print(f"row {i + 1} `{spec['label']}`: {row['command']}", flush=True)
        log = run.parent / f"{name}.log"
        rc, wall, rss, cut = run_until(cmd, log, deadline, env)
        m = _metrics(run) if rc == 0 and not cut else None
        row.update(summarize(m, wall, rss, darken_s))
        ok = True
        if m is not None:
            row["status"] = "ok"
        elif cut:
            steps, secs = _progress(run)
            row.update(steps=steps, train_seconds=secs, steps_per_second=steps / secs if steps and secs else None,
                       total_seconds=None)
            row["status"] = f"cut off at --limit {args.limit:g} s"
        else:
            ok = False
            row["status"] = f"failed (exit {rc}, {log.name})"
            tail = log.read_text(errors="replace").splitlines()[-10:]
            print("\n".join(f"    | {line}" for line in tail), file=sys.stderr, flush=True)
        shutil.rmtree(cache, ignore_errors=True)  # a 12 MP row's caches are GBs; the next row makes its own
        if row["status"] == "ok":
            atomic_write_text(run.parent / f"{name}.row.json", json.dumps(row, indent=1))
        print(f"  row {i + 1} {row['status']} in {wall:.0f} s: first step "
              f"{_num(row.get('time_to_first_step'), '.1f')} s, {_num(row.get('steps_per_second'), '.2f')} steps/s, "
              f"PSNR {_num(row.get('psnr'), '.2f')}", flush=True)
        with lock:
            table_rows[i] = row
            write_report(args.out, report, table_rows)
        return ok

    if args.side_by_side and len(rows) > 1:  # every row at once on the one device: PSNR, not times
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=len(rows)) as pool:
            failed = not all(pool.map(lambda a: run_row(*a), list(enumerate(rows))))
    else:
        failed = not all([run_row(i, spec) for i, spec in enumerate(rows)])
    report["total_seconds"] = round(time.monotonic() - t0, 1)
    md = write_report(args.out, report, table_rows)
    print(md)
    print(f"table: {args.out / 'bigraw.md'}, figures: {args.out / 'bigraw.json'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
