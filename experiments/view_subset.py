"""A scene folder that trains on every k-th of its training views (issue 64; notes/2026-11-29-denoiser-same-photons.md
§2): the question whether a lighter luma prior pays only where enough views average each point needs the same
scene with fewer views. The images, poses and points are the scene's own (linked, not copied); split.json and
transforms_train.json list the kept views; the test views are unchanged.

    python experiments/view_subset.py SCENE OUT --every 5      # fox-dark: 44 -> 9 training views

Then e.g. `python -m retinexgs.bench quality --scenes OUT --raw-ladder 1000e --ladder-paths raw --configs default
ablations/denoise_luma_0.4 --seeds 0,1` (the ladder darkens the folder's high/ photos, as for the scene itself).
"""
import argparse
import json
import os
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--every", type=int, default=5, help="keep training views 0, k, 2k, ...")
    args = ap.parse_args()
    split_path = args.scene / "split.json"
    if not split_path.is_file():
        raise SystemExit(f"{args.scene} has no split.json to take training views from")
    if args.out.exists():
        raise SystemExit(f"{args.out} exists: give a new folder")
    args.out.mkdir(parents=True)
    for entry in args.scene.iterdir():  # everything but the two files rewritten below, linked
        if entry.name not in ("split.json", "transforms_train.json"):
            os.symlink(entry.resolve(), args.out / entry.name)
    split = json.loads(split_path.read_text())
    split["train"] = split["train"][::max(1, args.every)]
    (args.out / "split.json").write_text(json.dumps(split, indent=1))
    frames_path = args.scene / "transforms_train.json"
    if frames_path.is_file():
        meta = json.loads(frames_path.read_text())
        meta["frames"] = [f for f in meta["frames"] if Path(f["file_path"]).name in set(split["train"])]
        (args.out / "transforms_train.json").write_text(json.dumps(meta, indent=1))
    print(f"{args.out}: {len(split['train'])} training views, {len(split.get('test', []))} test views")


if __name__ == "__main__":
    main()
