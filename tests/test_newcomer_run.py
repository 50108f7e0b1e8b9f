"""Issue 50, the run side: `demo --overwrite` replaces only what the demo made; Ctrl-C (and SIGTERM) during
`train` leaves a checkpoint of the step it stopped at, which `--resume` continues; `darken` on a folder it cannot
write, or a full disk, says so in one line and leaves nothing; `noise` shows progress; `--gpus N --device cpu`
says what it starts."""
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from retinexgs.cli import main
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.run.checkpoint import list_checkpoints, load_checkpoint

REPO = Path(__file__).resolve().parent.parent


# ---- demo --overwrite --------------------------------------------------------------------------------------

def test_demo_overwrite_replaces_only_its_scene_and_run(tmp_path, monkeypatch, capsys):
    """docs/usage.md puts `render --out retinexgs-demo/exposure-X` folders into the demo folder and a user adds
    notes: `demo --overwrite` must keep them and replace only scene/ and run/."""
    import retinexgs.demo.synthetic as synthetic
    import retinexgs.train.runner as runner

    out = tmp_path / "retinexgs-demo"
    for name in ("scene", "run", "exposure-0.5", "exposure-2"):
        (out / name).mkdir(parents=True)
        (out / name / "old.png").write_bytes(b"earlier")
    (out / ".retinexgs-demo").write_text("made by `retinexgs demo`\n")
    # what the earlier demo recorded as its own (issue 62: anything else in scene/ or run/ is refused)
    (out / ".retinexgs-demo-files.json").write_text(json.dumps({"files": ["run/old.png", "scene/old.png"]}))
    (out / "notes.txt").write_text("my notes")
    made = {}

    def fake_scene(folder):
        folder.mkdir(parents=True)
        made["scene_existed_before"] = (folder / "old.png").exists()
        return folder

    def fake_train(scene, run, *a, **k):
        made["run_existed_before"] = (run / "old.png").exists()
        run.mkdir(parents=True, exist_ok=True)
        return None

    monkeypatch.setattr(synthetic, "make_demo_scene", fake_scene)
    monkeypatch.setattr(runner, "train_run", fake_train)
    assert main(["demo", "--out", str(out), "--overwrite", "--device", "cpu", "--quiet"]) == 0
    assert made == {"scene_existed_before": False, "run_existed_before": False}
    assert (out / "notes.txt").read_text() == "my notes"
    for name in ("exposure-0.5", "exposure-2"):
        assert (out / name / "old.png").read_bytes() == b"earlier"
    said = capsys.readouterr().out
    assert "kept: exposure-0.5, exposure-2, notes.txt" in said, said


def test_demo_without_overwrite_still_refuses_and_touches_nothing(tmp_path, capsys):
    out = tmp_path / "d"
    (out / "run").mkdir(parents=True)
    (out / ".retinexgs-demo").write_text("x")
    assert main(["demo", "--out", str(out), "--device", "cpu", "--quiet"]) == 2
    assert "pass --overwrite" in capsys.readouterr().err
    assert (out / "run").is_dir()


# ---- Ctrl-C / SIGTERM during train ---------------------------------------------------------------------------

def _env():
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in [env.get("PYTHONPATH")] if p])
    return env


SETTINGS = ["steps=400", "checkpoint.every=1000", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
            "model.max_init_points=200", "decomposer.method=lime", "eval.lpips=false"]


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_stopped_train_checkpoints_the_step_it_stopped_at_and_resumes_from_it(tmp_path, signum, code):
    scene = make_demo_scene(tmp_path / "scene", n_train=3, n_test=1, width=24, height=18, n_points=200)
    run = tmp_path / "run"
    sets = [a for s in SETTINGS for a in ("--set", s)]
    log = tmp_path / "out.log"
    with open(log, "wb") as f:
        proc = subprocess.Popen([sys.executable, "-m", "retinexgs", "train", "--data", str(scene), "--out",
                                 str(run), "--config", "demo", *sets, "--quiet", "--device", "cpu"],
                                stdout=f, stderr=subprocess.STDOUT, env=_env())
    try:
        t0 = time.monotonic()
        lines = []
        while len(lines) < 5:  # a few trained steps, far from any checkpoint (every 1000)
            assert proc.poll() is None, log.read_text()
            assert time.monotonic() - t0 < 120, "no training progress"
            p = run / "train_log.jsonl"
            lines = [json.loads(x) for x in p.read_text().splitlines()] if p.is_file() else []
            time.sleep(0.05)
        proc.send_signal(signum)
        assert proc.wait(timeout=60) == code, log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
    text = log.read_text()
    assert "Traceback" not in text, text
    ckpts = list_checkpoints(run)
    assert len(ckpts) == 1, text
    step = int(load_checkpoint(ckpts[0])["step"])
    logged = max(r["step"] for r in map(json.loads, (run / "train_log.jsonl").read_text().splitlines()))
    assert 5 <= step < 400 and step == logged, (step, logged)
    assert f"stopped at step {step}: checkpoint" in text and "--resume" in text, text
    # --resume continues from exactly there (a short run: steps lowered to just past it)
    out = subprocess.run([sys.executable, "-m", "retinexgs", "train", "--out", str(run), "--resume", "--set",
                          f"steps={step + 2}", "--set", "eval.lpips=false", "--quiet", "--device", "cpu"],
                         capture_output=True, text=True, env=_env(), timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"(step {step})" in out.stdout + out.stderr
    assert int(load_checkpoint(list_checkpoints(run)[-1])["step"]) == step + 2


# ---- darken: unwritable --out, full disk ---------------------------------------------------------------------

def _photos(folder: Path, n: int = 2) -> Path:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        Image.fromarray(rng.integers(0, 255, (12, 16, 3), dtype=np.uint8)).save(folder / f"{i:04d}.png")
    return folder


def test_darken_into_a_folder_it_cannot_write_says_so_in_one_line(tmp_path, monkeypatch, capsys):
    import tempfile

    src = _photos(tmp_path / "photos")
    ro = tmp_path / "ro"
    ro.mkdir()
    real = tempfile.mkstemp

    def refuse(*a, **k):  # a read-only mount (chmod does not stop root, which CI may be)
        if str(k.get("dir", "")).startswith(str(ro)):
            raise OSError(errno.EROFS, "Read-only file system")
        return real(*a, **k)

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    assert main(["darken", "--data", str(src), "--out", str(ro / "dark"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot write in" in err and "Read-only file system" in err, err
    assert list(ro.iterdir()) == []


def test_darken_on_a_full_disk_names_it_and_leaves_nothing(tmp_path, monkeypatch, capsys):
    scene = tmp_path / "scene"
    _photos(scene / "high")
    (scene / "colmap_sparse").mkdir()
    (scene / "colmap_sparse" / "x.txt").write_text("x")
    (scene / "transforms_train.json").write_text("{}")
    out = tmp_path / "dark"

    def full(src, dst, *a, **k):  # copytree gathers its failures into one shutil.Error
        raise shutil.Error([(str(src), str(dst), "[Errno 28] No space left on device")])

    monkeypatch.setattr(shutil, "copytree", full)
    assert main(["darken", "--data", str(scene), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no space left on device" in err, err
    assert not out.exists()


def test_darken_failure_keeps_the_users_empty_out_folder(tmp_path, monkeypatch, capsys):
    src = _photos(tmp_path / "photos")
    out = tmp_path / "mine"
    out.mkdir()
    import retinexgs.data.sensor as sensor

    def boom(*a, **k):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(sensor, "write_image_atomic", boom)
    assert main(["darken", "--data", str(src), "--out", str(out), "--quiet"]) == 2
    assert "Input/output error" in capsys.readouterr().err
    assert out.is_dir() and list(out.iterdir()) == []


# ---- progress and small surprises ----------------------------------------------------------------------------

def test_noise_shows_progress_per_photo(tmp_path, capsys):
    src = _photos(tmp_path / "photos", n=3)
    assert main(["noise", "--data", str(src), "--photos", "3"]) == 0
    err = capsys.readouterr().err
    assert "noise" in err and "3/3" in err, err
    assert main(["noise", "--data", str(src), "--photos", "3", "--quiet"]) == 0
    assert "3/3" not in capsys.readouterr().err


def test_gpus_on_the_cpu_says_how_many_processes_share_the_cores(monkeypatch, capsys):
    from retinexgs.train import distributed

    started = []

    class FakeProc:
        def __init__(self, cmd, env=None):
            started.append(cmd)

        def wait(self, timeout=None):
            return 0

    monkeypatch.setattr(distributed.subprocess, "Popen", FakeProc)
    monkeypatch.setattr(distributed.os, "cpu_count", lambda: 2)
    assert distributed.relaunch(3, "cpu", ["train", "--gpus", "3", "--device", "cpu"]) == 0
    err = capsys.readouterr().err
    assert "3 training processes on the CPU" in err and "2 CPU cores" in err and "slower" in err, err
    assert started and "--nproc_per_node" in started[0]
