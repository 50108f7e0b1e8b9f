"""Contact sheets for the docs: one PNG per capture, input | today | new | truth, from two ``bench quality`` run
folders (e.g. ``decomposer.denoise: none`` against ``chroma``, issue 64).

    python experiments/contact_sheets.py --today RUNS_A --new RUNS_B --out DIR [--scenes SCENE ...]
        [--config default] [--new-config CONFIG] [--seed N] [--views 3] [--gain auto|G] [--names today,new]

Each run folder is a ``bench quality --runs`` folder: ``RUNS/SCENE_LABEL/CONFIG/seedN/`` with ``eval``'s
``metrics.json`` and side-by-side PNGs (``renders/test/NAME.png``). The panels are cut from those PNGs by
:func:`retinexgs.bench.quality.run_panels`, so the input is the dark view as the model trained on it, the truth the
scene's normal-light photo of that test view as ``eval`` scored it (the same size as the renders). The input is
brightened for display in linear light by a stated gain (``--gain``; ``auto``: the capture's truth-over-input
ratio of mean linear light over the sheet's views, to two significant digits), named in its column's label.
``--scenes``: scene folders (as given to ``bench quality``) or their labels; default every capture both folders
hold. One sheet per capture, ``DIR/sheet_LABEL.png``; an existing sheet is kept unless ``--overwrite``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from retinexgs.bench.quality import config_slug, run_panels, write_sheet
from retinexgs.data.scene import scene_label
from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear
from retinexgs.errors import UserError


def find_runs(root: Path, config: str) -> Dict[str, Dict[int, Path]]:
    """{scene label: {seed: run folder}} of the evaluated runs of ``config`` under a ``bench quality`` folder."""
    found: Dict[str, Dict[int, Path]] = {}
    for m in sorted(root.glob(f"**/{config_slug(config)}/seed*/metrics.json")):
        run = m.parent
        seed = run.name[len("seed"):]
        label = run.parent.parent.relative_to(root).as_posix()
        if seed.isdigit() and label != ".":
            found.setdefault(label, {})[int(seed)] = run
    return found


def _metrics(run: Path) -> dict:
    """A run's metrics.json, UserError when it is not an evaluated run's."""
    import json

    try:
        m = json.loads((run / "metrics.json").read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{run / 'metrics.json'}: not readable ({exc})") from None
    if not isinstance(m, dict) or not m.get("views"):
        raise UserError(f"{run / 'metrics.json'}: no evaluated test views (was eval skipped?)")
    return m


def brighten(img: Image.Image, gain: float) -> Image.Image:
    """The sRGB image ``img`` with its linear light times ``gain`` (clipped at white), for display."""
    lin = srgb_to_linear(np.asarray(img, dtype=np.float64) / 255.0) * gain
    return Image.fromarray(np.round(linear_to_srgb(np.clip(lin, 0.0, 1.0)) * 255.0).astype(np.uint8))


def auto_gain(inputs: Sequence[Image.Image], truths: Sequence[Image.Image]) -> float:
    """The truth's mean linear light over the input's, over all the given views, to two significant digits."""
    def mean_light(imgs: Sequence[Image.Image]) -> float:
        return float(np.mean([srgb_to_linear(np.asarray(i, dtype=np.float64) / 255.0).mean() for i in imgs]))

    low = mean_light(inputs)
    if low <= 0:
        return 1.0  # a black input: no gain shows anything, so none is claimed
    ratio = max(mean_light(truths) / low, 1.0)  # never darken the input
    return float(f"{ratio:.2g}")


def capture_sheet(label: str, today: Path, new: Path, out: Path, names: Tuple[str, str], views: int,
                  gain: Optional[float]) -> Path:
    """Write ``out``: input (brightened) | today | new | truth for the first ``views`` test views both runs hold."""
    m_today, m_new = _metrics(today), _metrics(new)
    in_new = {Path(v["view"]).stem for v in m_new["views"]}
    stems = [Path(v["view"]).stem for v in m_today["views"] if Path(v["view"]).stem in in_new][:views]
    if not stems:
        raise UserError(f"{label}: the two runs ({today}, {new}) share no test view")
    panels = []
    for stem in stems:
        for run in (today, new):
            if not (run / "renders" / "test" / f"{stem}.png").is_file():
                raise UserError(f"{run}: no render of test view {stem} (renders/test/{stem}.png); run eval again")
        low, out_today, truth = run_panels(today, m_today, stem)
        _, out_new, _ = run_panels(new, m_new, stem)
        if out_new.size != out_today.size:
            raise UserError(f"{label}, view {stem}: the runs' renders differ in size ({out_today.size[0]}x"
                            f"{out_today.size[1]} and {out_new.size[0]}x{out_new.size[1]}); use runs at one size")
        panels.append((stem, low, out_today, out_new, truth))
    g = gain if gain is not None else auto_gain([p[1] for p in panels], [p[4] for p in panels])
    rows = [([brighten(low, g), a, b, truth],
             # a label too long for its column keeps its end (write_sheet): the names go last
             [f"{stem}: input x{g:g}", f"{today.name}: {names[0]}", f"{new.name}: {names[1]}", "truth"])
            for stem, low, a, b, truth in panels]
    return write_sheet(rows, out, "--out")


def _parse_gain(text: str) -> Optional[float]:
    if text == "auto":
        return None
    try:
        g = float(text)
    except ValueError:
        g = float("nan")
    if not (g > 0 and np.isfinite(g)):
        raise UserError(f"--gain must be 'auto' or a positive number, got {text!r}")
    return g


def main(argv: Sequence[str]) -> int:
    ap = argparse.ArgumentParser(prog="python experiments/contact_sheets.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--today", type=Path, required=True, help="the bench quality runs folder of today's result")
    ap.add_argument("--new", type=Path, required=True, help="the bench quality runs folder of the new result")
    ap.add_argument("--out", type=Path, required=True, help="the folder the sheets go to")
    ap.add_argument("--scenes", nargs="*", default=None, help="scene folders or labels (default: all in both)")
    ap.add_argument("--config", default="default", help="the config of the runs in --today (default: default)")
    ap.add_argument("--new-config", default=None, help="the config of the runs in --new (default: --config)")
    ap.add_argument("--seed", type=int, default=None, help="the seed to show (default: the lowest both hold)")
    ap.add_argument("--views", type=int, default=3, help="test views per sheet (default 3)")
    ap.add_argument("--gain", default="auto", help="the input's display gain in linear light, or auto")
    ap.add_argument("--names", default="today,new", help="the two result columns' names (default today,new)")
    ap.add_argument("--overwrite", action="store_true", help="replace sheets that exist in --out")
    args = ap.parse_args(list(argv))
    try:
        written = make_sheets(args)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for p in written:
        print(p)
    return 0


def make_sheets(args: argparse.Namespace) -> List[Path]:
    """The sheets of ``main``'s arguments, written; UserError for a bad argument or run folder."""
    gain = _parse_gain(args.gain)
    names = tuple(n.strip() for n in args.names.split(","))
    if len(names) != 2 or not all(names):
        raise UserError(f"--names must be two names with a comma (today,new), got {args.names!r}")
    if args.views < 1:
        raise UserError(f"--views must be at least 1, got {args.views}")
    for flag, root in (("--today", args.today), ("--new", args.new)):
        if not root.is_dir():
            raise UserError(f"{flag} {root} is not a folder")
    today = find_runs(args.today, args.config)
    new = find_runs(args.new, args.new_config or args.config)
    common = [label for label in today if label in new]
    if args.scenes:
        wanted = [scene_label(Path(s)) if Path(s).is_dir() else s for s in args.scenes]
        missing = [w for w in wanted if w not in common]
        if missing:
            raise UserError(f"no evaluated runs of {missing[0]} in both {args.today} and {args.new} "
                            f"(they share: {', '.join(common) or 'none'})")
        common = wanted
    if not common:
        raise UserError(f"{args.today} and {args.new} share no scene with evaluated runs of the config(s) given")
    jobs = []
    for label in common:
        seeds = sorted(set(today[label]) & set(new[label]))
        if args.seed is not None:
            if args.seed not in seeds:
                raise UserError(f"{label}: seed {args.seed} is not in both folders (both hold: {seeds or 'none'})")
            seeds = [args.seed]
        if not seeds:
            raise UserError(f"{label}: the two folders share no seed")
        out = args.out / f"sheet_{label.replace('/', '-')}.png"
        if out.exists() and not args.overwrite:
            raise UserError(f"{out} exists; pass --overwrite to replace it or choose another --out")
        jobs.append((label, today[label][seeds[0]], new[label][seeds[0]], out))
    return [capture_sheet(label, a, b, out, names, args.views, gain) for label, a, b, out in jobs]


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
