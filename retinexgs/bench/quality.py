"""Quality benchmark: train every (scene, config, seed), evaluate, and write one markdown table plus a contact
sheet per scene (low | each config | truth).

    python -m retinexgs.bench quality --scenes DIR... --configs NAME... --seeds N [--jobs K] [--runs DIR]

Runs go to ``RUNS/<scene>/<config>/seed<k>`` (``default`` = configs/default.yaml alone). A run whose
``metrics.json`` exists is reused, not retrained: seeds can be trained in several calls (``--seeds 1,2``) and
the table rebuilt from all of them (``--no-train``); a run cut off after a checkpoint is resumed from it. Jobs
run side by side as separate ``retinexgs train`` processes (several trainings share one GPU well: the training
step is launch-bound).
"""
from __future__ import annotations

import argparse
import json
import os
import queue
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Dict, List, Optional, Sequence, Tuple

import numpy as np

from retinexgs.data.scene import scene_label
from retinexgs.data.sensor import LADDER_RAW_BITS, NOISE_LADDER, RNG_RECORD, SensorModel, darken_scene
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write, atomic_write_text
from retinexgs.run.checkpoint import latest_checkpoint

if TYPE_CHECKING:  # type hints only: raw_sim and Pillow are imported where they are needed
    from PIL import Image

    from retinexgs.data.raw_sim import RawCamera


@dataclass(frozen=True)
class Job:
    """One training run of the benchmark."""

    scene: Path
    config: str
    seed: int
    run: Path

    @property
    def metrics_path(self) -> Path:
        return self.run / "metrics.json"


def config_slug(config: str) -> str:
    return config.replace("/", "-")


def parse_seeds(text: str) -> List[int]:
    """``3`` -> [0, 1, 2] (a count); ``1,2`` or ``0,`` -> [1, 2] or [0] (a list: any text with a comma)."""
    if "," in text:
        return [int(s) for s in text.split(",") if s.strip()]
    n = int(text)
    if n < 1:
        raise ValueError("--seeds must be a positive count or a comma-separated list")
    return list(range(n))


def plan(scenes: Sequence[Path], configs: Sequence[str], seeds: Sequence[int], runs: Path) -> List[Job]:
    return [Job(Path(s), c, k, runs / scene_label(Path(s)) / config_slug(c) / f"seed{k}")
            for s in scenes for c in configs for k in seeds]


def train_command(job: Job, device: str, steps: Optional[int], extra: Sequence[str]) -> List[str]:
    cmd = [sys.executable, "-m", "retinexgs", "train", "--data", str(job.scene), "--out", str(job.run),
           "--device", device, "--quiet", "--set", f"seed={job.seed}"]
    if job.config != "default":
        cmd += ["--config", job.config]
    if steps is not None:
        cmd += ["--set", f"steps={steps}"]
    for s in extra:
        cmd += ["--set", s]
    return cmd


RESUMED = "bench_resumed"  # marker in a run folder: the benchmark resumed it, so its train time is partial


def run_job(job: Job, device: str, steps: Optional[int], extra: Sequence[str], gpu: Optional[int] = None) -> str:
    """Train one job (its log goes to RUN.log); returns a one-line status. A run cut off earlier (e.g. by a
    device call's time limit) continues from its newest checkpoint, so the steps it trained are not paid for
    twice; it is marked (:data:`RESUMED`) and its train time, which then covers only the last segment, is left
    out of the table. Without a checkpoint it starts again. ``gpu``: the one GPU it may see
    (CUDA_VISIBLE_DEVICES), for ``--gpus``."""

    if job.metrics_path.is_file():
        return f"reused  {job.run}"
    cmd = train_command(job, device, steps, extra)
    resumed = job.run.exists() and latest_checkpoint(job.run) is not None
    if resumed:
        cmd = [sys.executable, "-m", "retinexgs", "train", "--out", str(job.run), "--resume", "--device", device,
               "--quiet"]
        (job.run / RESUMED).write_text(f"resumed from {latest_checkpoint(job.run).name}\n")
    elif job.run.exists():  # cut off before its first checkpoint: start it again
        shutil.rmtree(job.run)
    job.run.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    on_gpu = {} if gpu is None else {"env": {**os.environ, "CUDA_VISIBLE_DEVICES": str(gpu)}}
    with open(f"{job.run}.log", "a" if resumed else "w") as log:
        rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, **on_gpu).returncode
    status = "ok" if rc == 0 and job.metrics_path.is_file() else f"FAILED (exit {rc}, see {job.run}.log)"
    return f"{status:7s} {job.run} in {time.time() - t0:.0f} s" + (" (resumed)" if resumed else "")


def read_metrics(job: Job) -> Optional[Dict]:
    try:
        m = json.loads(job.metrics_path.read_text())
    except (OSError, ValueError):
        return None
    return m if "mean" in m else None


def _mean_std(values: Sequence[float], digits: int) -> str:
    if not values:
        return "–"
    mean = float(np.mean(values))
    if len(values) == 1:
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ± {float(np.std(values, ddof=1)):.{digits}f}"


def _with_lpips(values: Sequence[Optional[float]], digits: int = 3) -> str:
    """The cell's LPIPS part, ``" / mean ± std"``, when every one of ``values`` has it; else "" (runs evaluated
    before LPIPS was on by default)."""
    return f" / {_mean_std(list(values), digits)}" if values and all(v is not None for v in values) else ""


def table(jobs: Sequence[Job], configs: Sequence[str], aligned: bool = False) -> str:
    """Markdown: per scene and config PSNR / SSIM / LPIPS (mean ± sample std over seeds) and train time; then the
    mean over scenes (each seed's scene-mean, so its ± is the spread of the whole benchmark over seeds). A cell
    shows LPIPS only when all its runs have it (runs evaluated before it was on by default have two figures).

    ``aligned``: the figures after the "GT-mean" alignment instead (``psnr_gt_mean`` / ``ssim_gt_mean`` /
    ``lpips_gt_mean``, :func:`retinexgs.evaluate.metrics.gt_mean_align`); runs evaluated before those keys existed
    are left out."""
    kp, ks, kl = ("psnr_gt_mean", "ssim_gt_mean", "lpips_gt_mean") if aligned else ("psnr", "ssim", "lpips")
    scenes = list(dict.fromkeys(scene_label(j.scene) for j in jobs))
    results: Dict = {}
    low: Dict[str, tuple] = {}
    for j in jobs:
        m = read_metrics(j)
        if m is None or kp not in m["mean"]:
            continue
        s = scene_label(j.scene)
        secs = None if (j.run / RESUMED).is_file() else m.get("train", {}).get("train_seconds")
        count = m.get("train", {}).get("gaussians")
        results.setdefault((s, j.config), []).append((j.seed, m["mean"][kp], m["mean"][ks], secs, count,
                                                       m["mean"].get(kl)))
        # the dark photos are the same in every run of a scene: an older run (no LPIPS) does not hide a newer one's
        low_lpips = m["mean"].get("low_lpips", low.get(s, (None,) * 3)[2])
        low[s] = (m["mean"]["low_psnr"], m["mean"]["low_ssim"], low_lpips)
    head = "| config | " + " | ".join(scenes) + " | mean |"
    lines = [head, "|" + "---|" * (len(scenes) + 2)]
    if not aligned:  # the dark photo against its truth, as given (aligning it would undo what is being measured)
        lines.append("| low input | " + " | ".join(f"{low[s][0]:.2f} / {low[s][1]:.3f}{_with_lpips(low[s][2:])}"
                                                   if s in low else "–" for s in scenes) + " | – |")
    for c in configs:
        cells = []
        per_seed: Dict[int, List[tuple]] = {}
        for s in scenes:
            r = results.get((s, c), [])
            for seed, p, q, _, _, lp in r:
                per_seed.setdefault(seed, []).append((p, q, lp))
            secs = [t for _, _, _, t, _, _ in r if t is not None]
            counts = [n for _, _, _, _, n, _ in r if n is not None]
            # the Gaussian count beside the time: a change that densifies more also trains slower and may fit noise
            extra = [] if aligned else ([f"{np.mean(secs):.0f} s"] if secs else []) + (
                [f"{np.mean(counts) / 1000:.0f}k Gaussians"] if counts else [])
            cells.append(f"{_mean_std([r_[1] for r_ in r], 2)} / {_mean_std([r_[2] for r_ in r], 3)}"
                         + _with_lpips([r_[5] for r_ in r]) + (f" ({', '.join(extra)})" if extra else ""))
        full = [v for v in per_seed.values() if len(v) == len(scenes)]
        lp_full = [None if any(lp is None for *_, lp in v) else float(np.mean([lp for *_, lp in v])) for v in full]
        mean_cell = (f"{_mean_std([np.mean([p for p, _, _ in v]) for v in full], 2)} / "
                     f"{_mean_std([np.mean([q for _, q, _ in v]) for v in full], 3)}"
                     + _with_lpips(lp_full)) if full else "–"
        n = sorted({len(results.get((s, c), [])) for s in scenes})
        lines.append(f"| `{c}` (n={'/'.join(map(str, n))}) | " + " | ".join(cells) + f" | {mean_cell} |")
    if aligned:
        return "\n".join(lines) + "\n\nThe same runs after the \"GT-mean\" alignment of low-light enhancement: each " \
            "output scaled so that its grey mean equals its truth's, then PSNR (dB) / SSIM / LPIPS. What this " \
            "leaves out is the exposure level of the normal-light photos, which no method trained on the dark " \
            "photos alone can know; the plain figures above are the benchmark's.\n"
    return "\n".join(lines) + "\n\nPSNR (dB) / SSIM / LPIPS (AlexNet, lower is better; absent for runs evaluated " \
        "before it was on) on the test views against the normal-light photos, mean ± sample " \
        "std over seeds (n = seeds per scene); (s) = mean training time (of the runs trained in one go), then " \
        "the mean number of Gaussians at the end. The " \
        "mean column averages each seed's scene means (seeds with every scene only).\n"


def _seed_table(jobs: Sequence[Job], configs: Sequence[str], key: str, digits: int, caption: str) -> str:
    """Markdown: per scene and config the metric ``key`` of the runs' test-view means, mean ± sample std over seeds,
    the dark input's (``low_`` + key) first; runs evaluated before the key existed are left out ("–")."""
    scenes = list(dict.fromkeys(scene_label(j.scene) for j in jobs))
    values: Dict = {}
    low: Dict[str, float] = {}
    for j in jobs:
        m = read_metrics(j)
        if m is None or key not in m["mean"]:
            continue
        s = scene_label(j.scene)
        values.setdefault((s, j.config), []).append(m["mean"][key])
        if f"low_{key}" in m["mean"]:
            low[s] = m["mean"][f"low_{key}"]
    lines = ["| config | " + " | ".join(scenes) + " |", "|" + "---|" * (len(scenes) + 1),
             "| low input | " + " | ".join(f"{low[s]:.{digits}f}" if s in low else "–" for s in scenes) + " |"]
    for c in configs:
        lines.append(f"| `{c}` | " + " | ".join(_mean_std(values.get((s, c), []), digits) for s in scenes) + " |")
    return "\n".join(lines) + "\n\n" + caption + "\n"


def colour_table(jobs: Sequence[Job], configs: Sequence[str]) -> str:
    """Markdown: per scene and config the colour error ``delta_e_gt_mean`` (CIELAB ΔE of the average colours after
    the GT-mean alignment, :func:`retinexgs.evaluate.metrics.colour_error`), mean ± sample std over seeds, the
    dark input's first; runs evaluated before the key existed are left out ("–")."""
    return _seed_table(jobs, configs, "delta_e_gt_mean", 2,
                       "Colour error: CIELAB ΔE (1976) between the average colours of the output, brightness-aligned "
                       "to its truth (GT-mean), and of the truth; a colour cast raises it, the exposure does not "
                       "(issue 32). Lower is better.")


def linear_colour_table(jobs: Sequence[Job], configs: Sequence[str]) -> str:
    """Markdown: the colour error split in two (runs evaluated since 2026-11-28): ``delta_e_linear`` (the render's
    linear light before the tone, :func:`retinexgs.evaluate.metrics.colour_error_linear`) and
    ``delta_e_tone_floor`` (the truth itself through the run's tone, :func:`~retinexgs.evaluate.metrics.tone_colour_floor`)."""
    light = _seed_table(jobs, configs, "delta_e_linear", 2,
                        "Colour error of the light alone: CIELAB ΔE between the average colours of the render's linear "
                        "light (before the highlight shoulder, the sRGB curve and the clip), scaled to the truth's mean "
                        "luminance, and of the truth in linear light.")
    floor = _seed_table(jobs, configs, "delta_e_tone_floor", 2,
                        "The tone's own cost: the colour error (as in the ΔE table) of the truth itself sent through the "
                        "run's tone at the run's exposure (metrics.json's exposure_ratio), what a render with exactly the "
                        "truth's light, exposed as the run exposes it, would score.")
    return light + "\n" + floor


def black_table(jobs: Sequence[Job], configs: Sequence[str]) -> str:
    """Markdown: per scene and config the black lift ``black_lift`` (:func:`retinexgs.evaluate.metrics.black_lift`),
    mean ± sample std over seeds, the dark input's first; runs evaluated before the key existed are left out."""
    return _seed_table(jobs, configs, "black_lift", 4,
                       "Black lift: the output's 1st percentile in linear light, brightness-aligned to its truth "
                       "(GT-mean), minus the truth's, averaged over the channels; positive = lifted blacks (clipped "
                       "sensor noise), negative = crushed, 0 = the truth's (issue 32).")


def chroma_table(jobs: Sequence[Job], configs: Sequence[str]) -> str:
    """Markdown: per scene and config the colour-noise figure ``chroma_noise``
    (:func:`retinexgs.evaluate.metrics.chroma_noise`), mean ± sample std over seeds, the dark input's first; runs
    evaluated before the key existed are left out ("–")."""
    return _seed_table(jobs, configs, "chroma_noise", 2,
                       "Chroma noise: the energy of the output's CIELAB a*/b* at scales of 2-32 px (a difference of "
                       "Gaussians), brightness-aligned to its truth (GT-mean), over the truth's in the same band; "
                       "1.0 = as much colour structure as the truth, colour speckle and blotches score far above, a "
                       "cast does not count (issue 64). Lower is better down to 1.0.")


def contact_sheet(jobs: Sequence[Job], configs: Sequence[str], scene: str, out: Path, views: int = 2) -> Optional[Path]:
    """low | each config (lowest seed) | truth for the first ``views`` test views, from the runs' side-by-side
    PNGs (their first panel is the low input, the second the output, the last the normal-light truth). Each column
    is labelled with its config and seed: configs run with different seeds show different seeds."""
    chosen: Dict[str, Job] = {}
    for j in sorted(jobs, key=lambda j: j.seed):
        if scene_label(j.scene) == scene and j.config not in chosen and read_metrics(j) is not None:
            chosen[j.config] = j
    # Runs copied without their renders (e.g. from another machine) are left out of the sheet.
    chosen = {c: j for c, j in chosen.items()
              if all((j.run / "renders" / "test" / f"{Path(v['view']).stem}.png").is_file()
                     for v in read_metrics(j)["views"][:views])}
    if not chosen:
        return None
    first = chosen[next(iter(chosen))]
    m = read_metrics(first)
    names = [Path(v["view"]).stem for v in m["views"]][:views]
    rows = []
    for name in names:
        cols, labels = [], []
        for k, c in enumerate(c for c in configs if c in chosen):
            low, output, truth = run_panels(chosen[c].run, read_metrics(chosen[c]), name)
            if k == 0:
                cols.append(low)
                labels.append("low input")
            cols.append(output)
            labels.append(f"{c}, seed {chosen[c].seed}")
        cols.append(truth)
        labels.append("truth")
        rows.append((cols, labels))
    return write_sheet(rows, out)


def run_panels(run: Path, metrics: Dict, name: str) -> Tuple["Image.Image", "Image.Image", "Image.Image"]:
    """(low input, output, truth) of test view ``name`` (a file stem) from a run's side-by-side PNG (``eval``'s
    ``renders/test/NAME.png``: its first panel is the low input, the second the output, the last the truth), below
    the strip naming the panels; ``metrics``: the run's metrics.json."""
    from PIL import Image

    img = Image.open(run / "renders" / "test" / f"{name}.png").convert("RGB")
    top = int(metrics.get("label_rows", 0))  # the strip naming the panels
    img = img.crop((0, top, img.width, img.height))
    h = img.height
    w = img.width // (5 if metrics.get("panels", "").count("|") == 4 else 3)
    return img.crop((0, 0, w, h)), img.crop((w, 0, 2 * w, h)), img.crop((img.width - w, 0, img.width, h))


def write_sheet(rows: Sequence[Tuple[Sequence["Image.Image"], Sequence[str]]], out: Path,
                elsewhere: str = "--runs") -> Path:
    """Write a contact sheet: one row per ``(images, labels)``, every image one size, each labelled above;
    ``elsewhere``: the caller's option naming another place to write, for a full disk's message."""
    from PIL import Image, ImageDraw

    w, h = rows[0][0][0].size
    pad = 14
    sheet = Image.new("RGB", (w * len(rows[0][0]), (h + pad) * len(rows)), "white")
    draw = ImageDraw.Draw(sheet)
    for r, (cols, labels) in enumerate(rows):
        for k, (img, label) in enumerate(zip(cols, labels)):
            sheet.paste(img, (k * w, r * (h + pad) + pad))
            # too long for the column: keep the end (the seed and the config's own name)
            fit = max(4, w // 6)
            draw.text((k * w + 2, r * (h + pad) + 1), label if len(label) <= fit else ".." + label[-fit + 2:],
                      fill="black")
    # a temporary name of its own: two benches sharing --runs write the same sheet at once
    atomic_write(out, lambda f: sheet.save(f, format="PNG"), elsewhere)
    return out


def ladder_scenes(scenes: Sequence[Path], root: Path, exposure: float) -> List[Path]:
    """Every scene darkened at every level of the noise ladder (made once: a level whose sensor.json records the
    same model is reused), as ``root/SCENE@LEVEL`` folders, scene-major."""
    out: List[Path] = []
    for scene in scenes:
        if not (Path(scene) / "high").is_dir():
            raise UserError(f"{scene} has no high/ folder of normal-light photos to darken")
        for label, full_well, read_noise in NOISE_LADDER:
            model = SensorModel(exposure=exposure, full_well=full_well, read_noise=read_noise)
            dst = root / f"{scene_label(Path(scene)).replace('/', '-')}@{label}"
            done = dst / "sensor.json"
            if done.is_file() and json.loads(done.read_text())["model"] == json.loads(json.dumps(asdict(model))):
                out.append(dst)
                continue
            if dst.exists():
                shutil.rmtree(dst)  # a level made with another model (or cut off): made again
            darken_scene(Path(scene), dst, model, seed=0, progress=False)
            print(f"noise ladder: {dst} ({label})", flush=True)
            out.append(dst)
    return out


def parse_gpus(text: str) -> List[int]:
    """``--gpus``: "" none, "4" GPUs 0-3, "2,3" those two."""
    text = text.strip()
    if not text:
        return []
    if "," in text:
        return [int(v) for v in text.split(",") if v.strip()]
    return list(range(int(text)))


def ladder_camera(label: str) -> "RawCamera":
    """The simulated camera of the raw ladder's level ``label``: the default camera, at the level's bit depth
    (:data:`retinexgs.data.sensor.LADDER_RAW_BITS`; 14 bit where it names none)."""
    from retinexgs.data.raw_sim import RawCamera

    return RawCamera(bits=LADDER_RAW_BITS.get(label, RawCamera.bits))


def _ladder_record(path: Path) -> Optional[dict]:
    """{"model", "bits", "rng"} of a raw ladder level's sensor.json (what decides whether it is reused: the random
    streams' scheme too, since a level drawn by an older one holds other noise); None if unreadable."""
    try:
        data = json.loads(path.read_text())
        return {"model": data["model"], "bits": data["camera"]["bits"], "rng": data.get("rng")}
    except (OSError, ValueError, KeyError, TypeError):
        return None


def ladder_paths(text: str) -> List[str]:
    """The paths of ``--ladder-paths`` (a comma list of raw and jpeg), UserError (one line) on anything else."""
    paths = [v for v in text.split(",") if v]
    bad = [v for v in paths if v not in ("raw", "jpeg")]
    if bad or not paths:
        raise UserError(f"--ladder-paths must be raw, jpeg or raw,jpeg, got {text!r}")
    return paths


def raw_ladder_scenes(scenes: Sequence[Path], root: Path, exposure: float, levels: Sequence[str]) -> List[Path]:
    """Every scene captured by the raw simulator (``darken --raw``, :func:`ladder_camera`) at each of ``levels``
    of the noise ladder: ``root/SCENE@LEVEL-raw`` (the DNGs) beside ``root/SCENE@LEVEL-jpeg`` (the camera's JPEGs
    of the same noisy mosaics), so that the two paths train on the same photons (issue 52). Made once: a level
    whose sensor.json records the same model, bit depth and random streams is reused."""
    known = {label: (fw, rn) for label, fw, rn in NOISE_LADDER}
    bad = [lv for lv in levels if lv not in known]
    if bad:
        raise UserError(f"unknown ladder level {bad[0]!r} (levels: {', '.join(known)})")
    out: List[Path] = []
    for scene in scenes:
        if not (Path(scene) / "high").is_dir():
            raise UserError(f"{scene} has no high/ folder of normal-light photos to darken")
        for label in levels:
            full_well, read_noise = known[label]
            model = SensorModel(exposure=exposure, full_well=full_well, read_noise=read_noise)
            camera = ladder_camera(label)
            base = root / f"{scene_label(Path(scene)).replace('/', '-')}@{label}"
            pair = [base.with_name(base.name + "-raw"), base.with_name(base.name + "-jpeg")]
            done = [p / "sensor.json" for p in pair]
            want = json.loads(json.dumps({"model": asdict(model), "bits": camera.bits, "rng": RNG_RECORD}))
            if all(d.is_file() and _ladder_record(d) == want for d in done):
                out.extend(pair)
                continue
            tmp = base.with_name(f".tmp-{base.name}")
            for p in (*pair, tmp):
                if p.exists():
                    shutil.rmtree(p)  # a level made with another model (or cut off): made again
            darken_scene(Path(scene), tmp, model, seed=0, progress=False, raw=camera)
            for p, sub in zip(pair, ("raw", "jpeg")):  # each holds its own sensor.json (darken writes it there)
                (tmp / sub).rename(p)
            shutil.rmtree(tmp)
            print(f"raw ladder: {pair[0]} and {pair[1].name} ({label})", flush=True)
            out.extend(pair)
    return out


def main(argv: Sequence[str]) -> int:
    ap = argparse.ArgumentParser(prog="python -m retinexgs.bench quality", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", type=Path, required=True, help="scene folders")
    ap.add_argument("--configs", nargs="+", default=["default"],
                    help="config names in configs/ (default, paper, ablations/baseline_pre, ...)")
    ap.add_argument("--seeds", default="3", help="a count N (seeds 0..N-1) or a list with a comma: 1,2 or 0, (default 3)")
    ap.add_argument("--runs", type=Path, default=Path("runs/quality"), help="where the runs go (reused when done)")
    ap.add_argument("--jobs", type=int, default=4, help="trainings side by side (default 4; per GPU with --gpus)")
    ap.add_argument("--gpus", default="",
                    help="spread the trainings over GPUs, --jobs on each: a count (4: GPUs 0-3) or a list with a "
                         "comma (2,3); empty: all on --device")
    ap.add_argument("--device", default="auto", help="cuda, cpu or auto")
    ap.add_argument("--steps", type=int, default=None, help="override every config's steps")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="extra override for every run")
    ap.add_argument("--out", type=Path, default=None, help="markdown file (default RUNS/quality.md)")
    ap.add_argument("--no-train", action="store_true", help="only tabulate the runs that exist")
    ap.add_argument("--noise-ladder", action="store_true",
                    help="train each scene's normal-light photos (high/) darkened at every level of the noise "
                         "ladder instead (retinexgs.data.sensor.NOISE_LADDER: clean to 800 e- full well, read "
                         "noise 6 e-), each level a column SCENE@LEVEL; the dark scenes go to RUNS/ladder/")
    ap.add_argument("--ladder-exposure", type=float, default=0.05, help="the ladder's exposure k (default 0.05)")
    ap.add_argument("--raw-ladder", default=None, metavar="LEVELS",
                    help="train each scene captured by the raw simulator at these ladder levels (comma list, e.g. "
                         "clean,1500e,1000e,800e; 800e's DNGs are 12 bit, the others 14): columns SCENE@LEVEL-raw "
                         "(DNGs) and SCENE@LEVEL-jpeg (the camera's JPEGs of the same captures); the dark scenes go "
                         "to RUNS/ladder/")
    ap.add_argument("--ladder-paths", default="raw,jpeg", metavar="PATHS",
                    help="with --raw-ladder: which of each capture's two paths to train, raw, jpeg or raw,jpeg "
                         "(default both)")
    args = ap.parse_args(list(argv))
    for s in args.scenes:
        if not s.is_dir():
            print(f"scene folder {s} does not exist", file=sys.stderr)
            return 2
    if args.noise_ladder:
        try:
            args.scenes = ladder_scenes(args.scenes, args.runs / "ladder", args.ladder_exposure)
        except UserError as exc:
            print(f"--noise-ladder: {exc}", file=sys.stderr)
            return 2
    if args.raw_ladder:
        try:
            paths = ladder_paths(args.ladder_paths)
            args.scenes = [s for s in raw_ladder_scenes(args.scenes, args.runs / "ladder", args.ladder_exposure,
                                                        [v for v in args.raw_ladder.split(",") if v])
                           if s.name.rsplit("-", 1)[-1] in paths]
        except UserError as exc:
            print(f"--raw-ladder: {exc}", file=sys.stderr)
            return 2
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        print(f"--seeds {args.seeds!r}: {exc}", file=sys.stderr)
        return 2
    jobs = plan(args.scenes, args.configs, seeds, args.runs)
    if not args.no_train:
        t0 = time.time()
        # Longest scenes first would balance better; the plan order (scene-major) keeps similar jobs apart.
        order = sorted(jobs, key=lambda j: (j.seed, j.config, str(j.scene)))
        slots: "queue.Queue[Optional[int]]" = queue.Queue()
        try:
            gpus = parse_gpus(args.gpus)
        except ValueError:
            print(f"--gpus {args.gpus!r}: a count or a comma list of GPU indices", file=sys.stderr)
            return 2
        for _ in range(max(1, args.jobs)):
            for g in gpus or [None]:
                slots.put(g)

        def on_a_slot(j: Job) -> str:
            g = slots.get()
            try:
                return run_job(j, "cuda" if g is not None else args.device, args.steps, args.set, g)
            finally:
                slots.put(g)

        with ThreadPoolExecutor(slots.qsize()) as pool:
            for line in pool.map(on_a_slot, order):
                print(line, flush=True)
        print(f"{len(jobs)} runs in {time.time() - t0:.0f} s", flush=True)
    md = table(jobs, args.configs)
    if any(m is not None and "psnr_gt_mean" in m["mean"] for m in map(read_metrics, jobs)):
        md += "\n" + table(jobs, args.configs, aligned=True)
    if any(m is not None and "delta_e_gt_mean" in m["mean"] for m in map(read_metrics, jobs)):
        md += "\n" + colour_table(jobs, args.configs)
    if any(m is not None and "delta_e_linear" in m["mean"] for m in map(read_metrics, jobs)):
        md += "\n" + linear_colour_table(jobs, args.configs)
    if any(m is not None and "black_lift" in m["mean"] for m in map(read_metrics, jobs)):
        md += "\n" + black_table(jobs, args.configs)
    if any(m is not None and "chroma_noise" in m["mean"] for m in map(read_metrics, jobs)):
        md += "\n" + chroma_table(jobs, args.configs)
    sheets = []
    for scene in dict.fromkeys(scene_label(j.scene) for j in jobs):
        path = contact_sheet(jobs, args.configs, scene, args.runs / f"sheet_{scene.replace('/', '-')}.png")
        if path is not None:
            sheets.append(path)
    md += "".join(f"\n![{p.stem}]({p.name})\n" for p in sheets)
    out = args.out or args.runs / "quality.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, md)
    print(md)
    print(f"table: {out}" + (f"; contact sheets: {', '.join(str(p) for p in sheets)}" if sheets else ""))
    failed = [j for j in jobs if read_metrics(j) is None]
    return 1 if failed and not args.no_train else 0
