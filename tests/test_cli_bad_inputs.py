"""Bad inputs at the command line: every command, given a missing path, an empty folder, a corrupt image, a
truncated checkpoint, a malformed transforms JSON or YAML config, an unknown ``--set`` key, ..., exits with
code 2 and one paragraph on stderr naming the file or the problem, no traceback, and writes nothing.

The cases are one table, ``CASES``: add a row per new case (``Case(id, argv, expect)``, with ``{placeholders}``
for the prepared inputs of ``SETUPS``). They run in-process through ``retinexgs.cli.main(argv)`` (fast);
``subprocess=True`` runs the real ``python -m retinexgs`` instead (exit code and stderr of the process).
"Writes nothing": the test folder's tree (names, sizes, modification times) is the same before and after,
except the documented caches a case lists in ``allow`` (none do today).
"""
import json
import os
import shutil
import subprocess
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Tuple

import pytest
import torch
import yaml

from retinexgs.cli import build_parser, main
from retinexgs.run.checkpoint import latest_checkpoint
from scenes import TINY_RUN, tiny_trained_run

REPO = Path(__file__).resolve().parent.parent
TINY = TINY_RUN
NOT_AN_IMAGE = b"these bytes are not an image\n" * 4


# ---- prepared inputs ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def originals(tmp_path_factory):
    """A tiny scene and a tiny trained run (3 steps), copied into each case's folder as needed."""
    scene, run = tiny_trained_run(tmp_path_factory.mktemp("originals"))
    return {"scene": scene, "run": run}


def _scene(root: Path, o: Dict) -> Path:
    """A copy of the scene as a user has it: without the caches the trained run left in it."""
    dst = root / "scene"
    shutil.copytree(o["scene"], dst, ignore=shutil.ignore_patterns("retinex_cache", "retinexgs_cache"))
    return dst


def _run(root: Path, o: Dict, scene: Path = None) -> Path:
    """A copy of the trained run (pointing at ``scene`` when given, else at the original scene)."""
    dst = root / "run"
    shutil.copytree(o["run"], dst)
    if scene is not None:
        data = yaml.safe_load((dst / "config.yaml").read_text())
        data["scene"] = str(scene)
        (dst / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return dst


def _corrupt_image(path: Path) -> None:
    path.write_bytes(NOT_AN_IMAGE)


def setup_corrupt_scene(root, o):
    _corrupt_image(_scene(root, o) / "low" / "0000.png")


def setup_truncated_image(root, o):
    """A photo cut short (an interrupted copy): its header reads, its pixels do not."""
    img = _scene(root, o) / "low" / "0000.png"
    data = img.read_bytes()
    img.write_bytes(data[: len(data) // 2])


def setup_truncated_checkpoint(root, o):
    ckpt = latest_checkpoint(_run(root, o))
    data = ckpt.read_bytes()
    ckpt.write_bytes(data[: len(data) // 2])


def setup_foreign_checkpoint(root, o):
    ckpt = latest_checkpoint(_run(root, o))
    torch.save([1, 2, 3], ckpt)


def setup_run_with_corrupt_scene(root, o):
    """The run's scene copied, with the normal-light image of its test view corrupt."""
    scene = _scene(root, o)
    _run(root, o, scene)
    _corrupt_image(scene / "high" / "0003.png")


def setup_photos(root, o, n=2, corrupt=False):
    photos = root / "photos"
    photos.mkdir()
    for i in range(n):
        shutil.copy(o["scene"] / "low" / f"{i:04d}.png", photos / f"{i:04d}.png")
    if corrupt:
        (photos / "9999.jpg").write_bytes(NOT_AN_IMAGE)


def setup_video(root, o, busy=False):
    """A 2-second MP4 of the scene's low photos (for `frames`), and with ``busy`` an --out holding a user's file."""
    import imageio_ffmpeg
    from PIL import Image

    frames = [Image.open(p).convert("RGB") for p in sorted((o["scene"] / "low").glob("*.png"))]
    w, h = frames[0].size
    g = imageio_ffmpeg.write_frames(str(root / "night.mp4"), (w, h), fps=10, macro_block_size=1)
    g.send(None)
    for i in range(20):
        g.send(frames[i % len(frames)].tobytes())
    g.close()
    if busy:
        (root / "busy").mkdir()
        (root / "busy" / "mine.txt").write_text("keep me\n")


def setup_black_photos(root, o):
    """Issue 62: two all-black photos (noise printed "full well inf e-, SNR 0.0")."""
    photos = root / "photos"
    photos.mkdir()
    for i in range(2):
        from PIL import Image
        Image.new("RGB", (32, 24)).save(photos / f"{i:04d}.png")


def setup_incomplete_model(root, o):
    """Issue 62: a photo folder whose colmap_sparse/0 holds only points3D.bin (SfM ran 50 s into the scene)."""
    setup_photos(root, o, n=2)
    model = root / "photos" / "colmap_sparse" / "0"
    model.mkdir(parents=True)
    (model / "points3D.bin").write_bytes(b"\0" * 8)


def setup_demo_with_user_file(root, o):
    """Issue 62: a demo folder the demo made (its record of its files), with a user's note added in run/."""
    out = root / "demo"
    for sub, name in (("scene", "a.png"), ("run", "metrics.json")):
        (out / sub).mkdir(parents=True)
        (out / sub / name).write_text("demo")
    (out / ".retinexgs-demo").write_text("")
    (out / ".retinexgs-demo-files.json").write_text(json.dumps({"files": ["scene/a.png", "run/metrics.json"]}))
    (out / "run" / "notes.txt").write_text("mine")


def setup_one_view(root, o):
    """The scene with one training frame left in transforms_train.json."""
    path = _scene(root, o) / "transforms_train.json"
    data = json.loads(path.read_text())
    data["frames"] = data["frames"][:1]
    path.write_text(json.dumps(data))


SETUPS: Dict[str, Callable[[Path, Dict], None]] = {
    "nothing": lambda root, o: None,
    "empty_dir": lambda root, o: (root / "empty").mkdir(),
    "a_file": lambda root, o: (root / "afile.txt").write_text("not a folder\n"),
    "scene": lambda root, o: _scene(root, o),
    "corrupt_scene": setup_corrupt_scene,
    "truncated_image": setup_truncated_image,
    "bad_json": lambda root, o: (_scene(root, o) / "transforms_train.json").write_text('{"frames": [ {"file_pa'),
    "json_without_frames": lambda root, o: (_scene(root, o) / "transforms_train.json").write_text('{"frame": []}'),
    "json_missing_image": lambda root, o: (_scene(root, o) / "low" / "0001.png").unlink(),
    "bad_yaml": lambda root, o: (_scene(root, o), (root / "bad.yaml").write_text("loss: [1, 2\n  w_tv: 0\n")),
    "yaml_not_a_mapping": lambda root, o: (_scene(root, o), (root / "list.yaml").write_text("- steps\n- 3\n")),
    "busy_out": lambda root, o: (_scene(root, o), (root / "busy").mkdir(), (root / "busy" / "mine.txt")
                                 .write_text("keep me\n")),
    "run": lambda root, o: _run(root, o),
    "truncated_checkpoint": setup_truncated_checkpoint,
    "foreign_checkpoint": setup_foreign_checkpoint,
    "run_bad_config": lambda root, o: (_run(root, o) / "config.yaml").write_text("method: [retinexgs\n"),
    "run_without_checkpoint": lambda root, o: shutil.rmtree(_run(root, o) / "checkpoints"),
    "run_corrupt_scene": setup_run_with_corrupt_scene,
    "run_scene_gone": lambda root, o: _run(root, o, root / "deleted_scene"),
    "photos_empty": lambda root, o: (root / "photos").mkdir(),
    "photos_one": lambda root, o: setup_photos(root, o, n=1),
    "photos_corrupt": lambda root, o: setup_photos(root, o, n=2, corrupt=True),
    "photos_two": lambda root, o: setup_photos(root, o, n=2),
    "one_view": setup_one_view,
    "video_busy_out": lambda root, o: setup_video(root, o, busy=True),
    "a_photo": lambda root, o: shutil.copy(o["scene"] / "low" / "0000.png", root / "night.png"),
    "photos_black": setup_black_photos,
    "incomplete_model": setup_incomplete_model,
    "demo_with_user_file": setup_demo_with_user_file,
}


# ---- the table ---------------------------------------------------------------------------------------------

@dataclass
class Case:
    id: str
    argv: List[str]          # {root} = the case's folder, {scene}, {run}, ... as prepared by ``setup``
    expect: str              # a distinctive substring of the error paragraph
    setup: str = "nothing"
    code: int = 2
    subprocess: bool = False
    allow: Tuple[str, ...] = ()  # documented caches the command may write even when it fails


T = ["--device", "cpu", "--quiet"]
SETS = [a for s in TINY for a in ("--set", s)]
TRAIN = ["train", "--out", "{root}/out", *T, "--config", "demo", *SETS]

CASES: List[Case] = [
    # train
    Case("train-missing-scene", TRAIN + ["--data", "{root}/missing"], "{root}/missing does not exist"),
    Case("train-missing-scene-subprocess", TRAIN + ["--data", "{root}/missing"], "{root}/missing does not exist",
         subprocess=True),
    Case("train-empty-folder", TRAIN + ["--data", "{root}/empty"], "holds no photos", "empty_dir"),
    Case("train-scene-is-a-file", TRAIN + ["--data", "{root}/afile.txt"], "is not a folder", "a_file"),
    Case("train-corrupt-image", TRAIN + ["--data", "{root}/scene"], "cannot read image {root}/scene/low/0000.png",
         "corrupt_scene"),
    Case("train-truncated-image", TRAIN + ["--data", "{root}/scene"], "cannot read image {root}/scene/low/0000.png",
         "truncated_image"),
    Case("train-malformed-transforms", TRAIN + ["--data", "{root}/scene"], "transforms_train.json is not valid JSON",
         "bad_json"),
    Case("train-transforms-without-frames", TRAIN + ["--data", "{root}/scene"], "expected an object with a 'frames'",
         "json_without_frames"),
    Case("train-transforms-missing-image", TRAIN + ["--data", "{root}/scene"], "0001", "json_missing_image"),
    Case("train-malformed-yaml", TRAIN + ["--data", "{root}/scene", "--config", "{root}/bad.yaml"],
         "{root}/bad.yaml is not valid YAML", "bad_yaml"),
    Case("train-yaml-not-a-mapping", TRAIN + ["--data", "{root}/scene", "--config", "{root}/list.yaml"],
         "must be a mapping", "yaml_not_a_mapping"),
    Case("train-missing-config", TRAIN + ["--data", "{root}/scene", "--config", "{root}/nosuch.yaml"],
         "nosuch.yaml' not found", "scene"),
    Case("train-unknown-set-key", TRAIN + ["--data", "{root}/scene", "--set", "loss.w_typo=1"],
         "unknown config key --set loss.w_typo (known", "scene"),
    Case("train-set-without-equals", TRAIN + ["--data", "{root}/scene", "--set", "steps"],
         "must look like key.sub=value", "scene"),
    Case("train-set-malformed-value", TRAIN + ["--data", "{root}/scene", "--set", "steps=[1"],
         "--set steps=[1", "scene"),
    Case("train-set-bad-value", TRAIN + ["--data", "{root}/scene", "--set", "steps=-3"],
         "steps must be a positive integer", "scene"),
    Case("train-bad-device", TRAIN + ["--data", "{root}/scene", "--device", "tpu"], "--device must be cpu",
         "scene"),
    Case("train-out-not-empty", ["train", "--data", "{root}/scene", "--out", "{root}/busy", *T], "already exists",
         "busy_out"),
    Case("train-no-data", ["train", "--out", "{root}/out", *T], "--data SCENE is required"),
    Case("train-no-out", ["train", "--data", "{root}/scene", *T], "the following arguments are required: --out",
         "scene"),
    Case("resume-missing-run", ["train", "--out", "{root}/missing", "--resume", *T], "is not a run folder"),
    Case("resume-truncated-checkpoint", ["train", "--out", "{root}/run", "--resume", *T],
         "step_000003.pt is unreadable", "truncated_checkpoint"),
    Case("resume-foreign-checkpoint", ["train", "--out", "{root}/run", "--resume", *T],
         "is not a RetinexGS checkpoint", "foreign_checkpoint"),
    Case("resume-malformed-config", ["train", "--out", "{root}/run", "--resume", *T],
         "{root}/run/config.yaml is not valid YAML", "run_bad_config"),
    Case("resume-unknown-set-key", ["train", "--out", "{root}/run", "--resume", "--set", "typo=1", *T],
         "unknown config key --set typo (known", "run"),
    # eval
    Case("eval-missing-run", ["eval", "--run", "{root}/missing", "--device", "cpu"], "is not a run folder"),
    Case("eval-empty-folder", ["eval", "--run", "{root}/empty", "--device", "cpu"], "no config.yaml", "empty_dir"),
    Case("eval-truncated-checkpoint", ["eval", "--run", "{root}/run", "--device", "cpu"],
         "step_000003.pt is unreadable", "truncated_checkpoint"),
    Case("eval-truncated-checkpoint-subprocess", ["eval", "--run", "{root}/run", "--device", "cpu"],
         "step_000003.pt is unreadable", "truncated_checkpoint", subprocess=True),
    Case("eval-foreign-checkpoint", ["eval", "--run", "{root}/run", "--device", "cpu"],
         "is not a RetinexGS checkpoint", "foreign_checkpoint"),
    Case("eval-malformed-config", ["eval", "--run", "{root}/run", "--device", "cpu"], "is not valid YAML",
         "run_bad_config"),
    Case("eval-no-checkpoint", ["eval", "--run", "{root}/run", "--device", "cpu"], "has no checkpoint",
         "run_without_checkpoint"),
    Case("eval-corrupt-image", ["eval", "--run", "{root}/run", "--device", "cpu"],
         "cannot read image {root}/scene/high/0003.png", "run_corrupt_scene"),
    Case("eval-scene-gone", ["eval", "--run", "{root}/run", "--device", "cpu"], "deleted_scene, does not exist",
         "run_scene_gone"),
    # demo (only the refusals: a real demo trains for minutes)
    Case("demo-out-is-a-file", ["demo", "--out", "{root}/afile.txt", *T], "--out {root}/afile.txt is a file", "a_file"),
    Case("demo-out-not-empty", ["demo", "--out", "{root}/busy", *T], "already exists", "busy_out"),
    # issue 62: --overwrite deleted the user's files inside run/ and scene/
    Case("demo-overwrite-keeps-the-users-files", ["demo", "--out", "{root}/demo", "--overwrite", *T], "run/notes.txt",
         "demo_with_user_file"),
    Case("demo-zero-steps", ["demo", "--out", "{root}/demo", "--steps", "0", *T], "--steps must be a positive"),
    Case("demo-negative-steps", ["demo", "--out", "{root}/demo", "--steps", "-5", *T], "--steps must be a positive"),
    # issue 36: --overwrite on a folder the demo did not make gave the message of a plain refusal
    Case("demo-overwrite-not-a-demo-folder", ["demo", "--out", "{root}/busy", "--overwrite", *T],
         "--overwrite only replaces a folder the demo made itself", "busy_out"),
    # issue 36: a single training view trained to 1 Gaussian
    Case("train-one-view", TRAIN + ["--data", "{root}/scene"], "has only 1 training view (low/0000.png); a 3D "
         "reconstruction needs at least 2 views", "one_view"),
    # decompose
    Case("decompose-missing-scene", ["decompose", "--data", "{root}/missing", "--quiet"], "not found: {root}/missing"),
    Case("decompose-empty-folder", ["decompose", "--data", "{root}/empty", "--quiet"], "no photos in", "empty_dir"),
    Case("decompose-scene-is-a-file", ["decompose", "--data", "{root}/afile.txt", "--quiet"], "got a file",
         "a_file"),
    Case("decompose-corrupt-image", ["decompose", "--data", "{root}/scene", "--method", "lime", "--quiet"],
         "cannot read image {root}/scene/low/0000.png", "corrupt_scene"),
    Case("decompose-truncated-image", ["decompose", "--data", "{root}/scene", "--method", "lime", "--quiet"],
         "cannot read image {root}/scene/low/0000.png", "truncated_image"),
    Case("decompose-malformed-transforms", ["decompose", "--data", "{root}/scene", "--quiet"],
         "transforms_train.json is not a valid transforms file", "bad_json"),
    Case("decompose-transforms-missing-image", ["decompose", "--data", "{root}/scene", "--quiet"],
         "are missing: {root}/scene/low/0001.png", "json_missing_image"),
    Case("decompose-bad-device", ["decompose", "--data", "{root}/scene", "--device", "tpu", "--quiet"],
         "invalid choice: 'tpu'", "scene"),
    # issue 36: a missing --images-subdir fell back to the scene folder silently
    Case("decompose-missing-images-subdir", ["decompose", "--data", "{root}/scene", "--images-subdir", "nope",
                                             "--method", "lime", "--quiet"],
         "--images-subdir nope: {root}/scene/nope is not a folder (it does not exist)", "scene"),
    # darken, noise (issue 32: the sensor model)
    Case("darken-missing-data", ["darken", "--data", "{root}/missing", "--out", "{root}/dark", "--quiet"],
         "{root}/missing is not a folder"),
    Case("darken-zero-exposure", ["darken", "--data", "{root}/scene", "--out", "{root}/dark", "--exposure", "0"],
         "--exposure must be in (0, 1]", "scene"),
    Case("darken-bad-cast", ["darken", "--data", "{root}/scene", "--out", "{root}/dark", "--cast", "1,1"],
         "expected three gains R,G,B", "scene"),
    Case("noise-empty-folder", ["noise", "--data", "{root}/photos"], "no photos in {root}/photos", "photos_empty"),
    # issue 62: all-black photos were "full well inf e-, SNR 0.0"
    Case("noise-all-black-photos", ["noise", "--data", "{root}/photos"], "is all zero (black)", "photos_black"),
    # issue 62: a model folder holding points3D.bin alone was "no model", and SfM wrote into the scene
    Case("train-incomplete-colmap-model", TRAIN + ["--data", "{root}/photos"],
         "colmap_sparse/0 is incomplete", "incomplete_model"),
    # sfm
    Case("sfm-missing-folder", ["sfm", "--images", "{root}/missing", "--quiet"], "{root}/missing does not exist"),
    Case("sfm-empty-folder", ["sfm", "--images", "{root}/photos", "--quiet"], "is empty", "photos_empty"),
    Case("sfm-one-photo", ["sfm", "--images", "{root}/photos", "--quiet"], "only one photo", "photos_one"),
    Case("sfm-corrupt-photo", ["sfm", "--images", "{root}/photos", "--quiet"],
         "cannot read image {root}/photos/9999.jpg", "photos_corrupt"),
    Case("sfm-images-is-a-file", ["sfm", "--images", "{root}/afile.txt", "--quiet"], "afile.txt", "a_file"),
    # issue 36: pycolmap's "Check failed", the second after feature extraction had written OUT/enhanced/
    Case("sfm-zero-features", ["sfm", "--images", "{root}/photos", "--max-features", "0", "--quiet"],
         "--max-features must be a positive number", "photos_two"),
    Case("sfm-negative-threads", ["sfm", "--images", "{root}/photos", "--enhance", "on", "--threads", "-5",
                                  "--quiet"], "--threads must be -1 (all CPU threads", "photos_two"),
    # frames (issue 62; more bad videos in test_frames_video.py)
    Case("frames-missing-video", ["frames", "--video", "{root}/night.mp4", "--out", "{root}/photos"],
         "--video {root}/night.mp4 does not exist"),
    Case("frames-text-file", ["frames", "--video", "{root}/afile.txt", "--out", "{root}/photos"],
         "is not a video ffmpeg can read", "a_file"),
    Case("frames-a-photo", ["frames", "--video", "{root}/night.png", "--out", "{root}/photos"],
         "is a still photo (PNG), not a video", "a_photo"),
    Case("frames-busy-out", ["frames", "--video", "{root}/night.mp4", "--out", "{root}/busy", "--quiet"],
         "--out {root}/busy is not empty (mine.txt)", "video_busy_out"),
    Case("frames-max-below-3", ["frames", "--video", "{root}/night.mp4", "--out", "{root}/photos", "--max", "2"],
         "--max must be at least 3", "video_busy_out"),
]

# ---- render / export (retinexgs.export; rows used only while those commands exist) ----------------------------
# Add rows here as the commands grow (e.g. a bad --maps, --path or --format value).
RENDER_EXPORT_CASES: List[Case] = [
    Case("render-missing-run", ["render", "--run", "{root}/missing", *T], "is not a run folder"),
    Case("render-truncated-checkpoint", ["render", "--run", "{root}/run", *T], "step_000003.pt is unreadable",
         "truncated_checkpoint"),
    Case("render-malformed-config", ["render", "--run", "{root}/run", *T], "is not valid YAML", "run_bad_config"),
    Case("render-fps-not-finite", ["render", "--run", "{root}/run", "--path", "orbit", "--fps", "inf", *T],
         "--fps must be a positive finite number", "run"),  # issue 36 (--frames 10^8: test_bad_inputs_data_export)
    Case("export-missing-run", ["export", "--run", "{root}/missing", "--out", "{root}/x.ply", *T],
         "is not a run folder"),
    Case("export-truncated-checkpoint", ["export", "--run", "{root}/run", "--out", "{root}/x.ply", *T],
         "step_000003.pt is unreadable", "truncated_checkpoint"),
    Case("export-malformed-config", ["export", "--run", "{root}/run", "--out", "{root}/x.ply", *T],
         "is not valid YAML", "run_bad_config"),
    # issue 36: an existing folder as --out suggested --force, which then refused it
    Case("export-out-is-a-folder", ["export", "--run", "{root}/run", "--out", "{root}/run", *T],
         "--out {root}/run is a folder; --out is the .ply file to write, e.g. --out {root}/run/point_cloud.ply", "run"),
    Case("export-out-is-a-folder-force", ["export", "--run", "{root}/run", "--out", "{root}/run", "--force", *T],
         "--out {root}/run is a folder; --out is the .ply file to write", "run"),
    # view (issue 14): the run and the address are checked before viser is needed; more in test_view_server.py.
    Case("view-missing-run", ["view", "--run", "{root}/missing", "--device", "cpu"], "is not a run folder"),
    Case("view-truncated-checkpoint", ["view", "--run", "{root}/run", "--device", "cpu"],
         "step_000003.pt is unreadable", "truncated_checkpoint"),
    Case("view-bad-port", ["view", "--run", "{root}/run", "--device", "cpu", "--port", "99999"],
         "--port must be 0..65535"),
    # bench (issue 62): the dispatcher of python -m retinexgs.bench; each benchmark checks its own options.
    Case("bench-unknown", ["bench", "nosuch"], "retinexgs bench: error: unknown benchmark 'nosuch'"),
    Case("bench-no-name", ["bench"], "choose one of raster, lr3m"),
]


def _commands() -> set:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return set(sub.choices)


_PRESENT = _commands()
ALL_CASES = CASES + [c for c in RENDER_EXPORT_CASES if c.argv[0] in _PRESENT]


# ---- the check ---------------------------------------------------------------------------------------------

def snapshot(root: Path) -> Dict[str, Tuple]:
    """Every file and folder under ``root``: relative path -> (kind, size, mtime_ns)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = p.lstat()
            out[str(p.relative_to(root))] = ("dir" if p.is_dir() else "file", 0 if p.is_dir() else st.st_size,
                                             0 if p.is_dir() else st.st_mtime_ns)
    return out


def _run_in_process(argv: List[str], capsys) -> Tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse errors
        code = exc.code if isinstance(exc.code, int) else 1
    except BaseException:  # noqa: BLE001 - a traceback is exactly what this test looks for
        captured = capsys.readouterr()
        return -1, captured.out, captured.err + "\nTraceback (escaped main):\n" + traceback.format_exc()
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _run_subprocess(argv: List[str], cwd: Path) -> Tuple[int, str, str]:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in [env.get("PYTHONPATH")] if p])
    p = subprocess.run([sys.executable, "-m", "retinexgs", *argv], cwd=cwd, env=env, capture_output=True,
                       text=True, timeout=120)
    return p.returncode, p.stdout, p.stderr


@pytest.mark.parametrize("case", ALL_CASES, ids=[c.id for c in ALL_CASES])
def test_bad_input(case, originals, tmp_path, capsys, monkeypatch, one_thread):
    root = tmp_path / "case"
    root.mkdir()
    SETUPS[case.setup](root, originals)
    monkeypatch.chdir(root)
    argv = [a.format(root=root) for a in case.argv]
    expect = case.expect.format(root=root)
    before = snapshot(root)
    before_originals = snapshot(originals["scene"].parent)
    capsys.readouterr()
    if case.subprocess:
        code, out, err = _run_subprocess(argv, root)
    else:
        code, out, err = _run_in_process(argv, capsys)
    report = f"argv {argv}\nexit {code}\nstdout:\n{out}\nstderr:\n{err}"
    assert "Traceback" not in out + err, report
    assert code == case.code, report
    err = err.strip()
    assert expect in err, f"expected {expect!r} in stderr\n{report}"
    assert "\n\n" not in err, f"stderr is more than one paragraph\n{report}"
    after = snapshot(root)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k)
                     and not any(k == a or k.startswith(a + os.sep) or f"{os.sep}{a}" in k for a in case.allow))
    assert not changed, f"the failed command wrote or changed {changed}\n{report}"
    assert snapshot(originals["scene"].parent) == before_originals, "the shared scene or run was modified"


def test_table_covers_every_command():
    """Every sub-command of the CLI has rows in the table (a new command needs its bad-input rows)."""
    covered = {c.argv[0] for c in ALL_CASES}
    assert _PRESENT <= covered, f"commands without bad-input cases: {sorted(_PRESENT - covered)}"
