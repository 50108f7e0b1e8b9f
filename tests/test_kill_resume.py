"""Crash-safe training: ``retinexgs train`` SIGKILLed at random (seeded) moments resumes from a complete
checkpoint every time and finally finishes and evaluates; a parameter turning non-finite stops the run
naming the parameter and the step, with the last good checkpoint intact and resumable.

The kill test runs the real command in subprocesses on a tiny scene with a checkpoint every 2 steps:
KILL_TRIALS kills, the first at a random moment from the process start (often during start-up, before the
first checkpoint), the others at a random delay after the process has trained its first step. Every
subprocess has a timeout and the whole test a deadline, so it cannot hang.
"""
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from retinexgs.data import load_scene
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.run.checkpoint import list_checkpoints, load_checkpoint
from retinexgs.config import read_yaml
from retinexgs.run.config import load_config
from retinexgs.train.trainer import Trainer, TrainingDiverged

KILL_TRIALS = 5
KILL_SEED = 2024
STEPS = 200
DEADLINE_S = 240.0  # the whole kill test; a normal run takes ~40 s on a loaded 2-core machine
PROCESS_TIMEOUT_S = 120.0
# A tiny, fast run that checkpoints every 2 steps (keeping 2) and densifies on the way (the number of
# Gaussians changes between checkpoints, which the resume must follow).
SETTINGS = [f"steps={STEPS}", "checkpoint.every=2", "checkpoint.keep=2", "log.every=1",
            "log.tensorboard=false", "model.sh_degree=1", "model.sh_degree_every=50",
            "model.max_init_points=300", "loss.enhance_from=60", "density.start=4", "density.every=8",
            "density.stop=120", "decomposer.method=lime", "eval.lpips=false"]
REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("scene") / "demo", n_train=4, n_test=2, width=40, height=30,
                           n_points=400)


def _env():
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in [env.get("PYTHONPATH")] if p])
    return env


def _finish(proc) -> int:
    """The process's exit code once it ends (killed if it outlives PROCESS_TIMEOUT_S: a hang fails the test)."""
    try:
        return proc.wait(timeout=PROCESS_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)


def _start(args, log_path: Path) -> subprocess.Popen:
    out = open(log_path, "wb")
    try:
        return subprocess.Popen([sys.executable, "-m", "retinexgs", "train", *args, "--quiet", "--device", "cpu"],
                                stdout=out, stderr=subprocess.STDOUT, env=_env(), cwd=log_path.parent)
    finally:
        out.close()


def _log_lines(run: Path):
    p = run / "train_log.jsonl"
    return p.read_text().splitlines() if p.is_file() else []


def _check_run_folder(run: Path, last_step: int) -> int:
    """After a kill: config readable, every listed checkpoint complete and loadable, the newest at least
    ``last_step``, every other file in checkpoints/ a temporary that the run never lists, every log line
    whole JSON. Returns the newest checkpoint's step (0 when there is none)."""
    if (run / "config.yaml").exists():
        assert "steps" in read_yaml(run / "config.yaml")
    listed = list_checkpoints(run)
    steps = []
    for p in listed:
        state = load_checkpoint(p)  # raises (fails the test) for a partial file
        assert int(state["step"]) == int(p.stem.split("_")[1])
        steps.append(int(state["step"]))
    newest = max(steps, default=0)
    assert newest >= last_step, f"checkpoint went back from step {last_step} to {newest}"
    ckdir = run / "checkpoints"
    others = [p for p in ckdir.iterdir() if p not in listed] if ckdir.is_dir() else []
    for p in others:  # only temporaries of an interrupted save, hidden and never listed
        assert p.name.startswith(".") and p.name.endswith(".tmp"), f"unexpected file {p}"
    for i, line in enumerate(_log_lines(run)):
        json.loads(line)  # a cut line would fail here
    return newest


def test_sigkill_at_random_moments_then_resume_finishes(tiny_scene, tmp_path):
    t_start = time.monotonic()
    rng = random.Random(KILL_SEED)
    run = tmp_path / "run"
    sets = [a for s in SETTINGS for a in ("--set", s)]
    fresh = ["--data", str(tiny_scene), "--out", str(run), "--config", "demo", *sets]
    last_step, kills, history = 0, 0, []
    for trial in range(KILL_TRIALS):
        assert time.monotonic() - t_start < DEADLINE_S, f"kill test over its deadline after {trial} trials"
        resume = (run / "config.yaml").is_file()
        args = ["--out", str(run), "--resume"] if resume else fresh
        out_path = tmp_path / f"trial{trial}.log"
        lines_before = len(_log_lines(run))
        proc = _start(args, out_path)
        try:
            if trial == 0:
                time.sleep(rng.uniform(0.5, 3.0))  # anywhere from start-up to the first steps
            else:
                t0 = time.monotonic()  # wait for this process's first trained step, then a random delay
                while len(_log_lines(run)) <= lines_before and proc.poll() is None:
                    assert time.monotonic() - t0 < PROCESS_TIMEOUT_S, "no training progress"
                    time.sleep(0.02)
                time.sleep(rng.uniform(0.05, 1.0))
            finished = proc.poll() is not None
            if not finished:
                proc.send_signal(signal.SIGKILL)
                kills += 1
            proc.wait(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=30)
        text = out_path.read_text(errors="replace")
        assert "Traceback" not in text, text
        if resume:  # the resumed process found the newest complete checkpoint (or none yet: step 0)
            assert f"(step {last_step})" in text or (last_step == 0 and "starting from step 0" in text), text
        step = _check_run_folder(run, last_step)
        history.append((trial, "resume" if resume else "fresh", "finished" if finished else "killed", step))
        last_step = step
        if finished:
            assert proc.returncode == 0, text
            break
    print("kill trials (trial, start, outcome, newest checkpoint step):", history)
    assert kills >= KILL_TRIALS - 1, history
    # A save killed mid-write leaves a hidden temporary: never listed, never loaded, swept by the next save.
    stale = run / "checkpoints" / ".step_999999.pt.k1ll3d.tmp"
    stale.parent.mkdir(exist_ok=True)
    stale.write_bytes(b"PK\x03\x04 cut short")
    assert stale not in list_checkpoints(run)
    # The last resume runs to the end, then evaluates.
    proc = _start(["--out", str(run), "--resume"], tmp_path / "final.log")
    rc = _finish(proc)
    text = (tmp_path / "final.log").read_text(errors="replace")
    assert rc == 0 and "Traceback" not in text, text
    assert f"(step {last_step})" in text or "already finished" in text, text
    assert _check_run_folder(run, last_step) == STEPS
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["mean"]["psnr"] > 0, metrics
    assert len(list((run / "renders" / "test").glob("*.png"))) == 2
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == [p.name for p in list_checkpoints(run)], \
        "a temporary of an interrupted save was left behind"
    assert len(list_checkpoints(run)) == 2
    assert time.monotonic() - t_start < DEADLINE_S, history


# ---- non-finite parameters ---------------------------------------------------------------------------------

TINY = ["steps=8", "checkpoint.every=3", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
        "model.sh_degree_every=2", "model.max_init_points=300", "loss.enhance_from=4", "density.start=100",
        "decomposer.method=lime"]


@pytest.mark.parametrize("param", ["gaussians.means", "gaussians.opacity_logits", "illumination"])
def test_non_finite_parameter_stops_with_the_name_and_step(tiny_scene, tmp_path, param, one_thread):
    """A NaN written into a parameter by the optimiser step stops training at that step, naming it; the
    checkpoints are untouched and a resume continues from the last good one to the end."""
    run = tmp_path / "run"
    run.mkdir()
    cfg = load_config(["demo"], TINY)
    scene = load_scene(tiny_scene)
    tr = Trainer(cfg, scene, run, "cpu", progress=False, log=lambda s: None)
    tr.train(stop_after=3)  # checkpoint at step 3
    good = {p.name: p.read_bytes() for p in (run / "checkpoints").iterdir()}
    params = dict(tr.model.named_parameters())
    name = param if param in params else next(n for n in params if n.startswith(param + "."))
    label = (f"Gaussian parameter {name.split('.', 1)[1]}" if name.startswith("gaussians.")
             else f"network parameter {name}")
    real_step = tr.optimizer.step

    def poisoned_step(*a, **k):
        result = real_step(*a, **k)
        if tr.step == 5:
            with torch.no_grad():
                params[name].view(-1)[0] = float("nan")
        return result

    tr.optimizer.step = poisoned_step
    with pytest.raises(TrainingDiverged, match=rf"^{label} became non-finite at step 5; the last good checkpoint"):
        tr.train()
    assert {p.name: p.read_bytes() for p in (run / "checkpoints").iterdir()} == good
    resumed = Trainer(cfg, scene, run, "cpu", resume=True, progress=False, log=lambda s: None)
    assert resumed.step == 3
    resumed.train()
    assert resumed.step == 8
    assert all(bool(torch.isfinite(p).all()) for p in resumed.model.parameters())
    assert max(int(p.stem.split("_")[1]) for p in list_checkpoints(run)) == 8


def test_cli_reports_divergence_in_one_line_with_exit_2(tiny_scene, tmp_path, monkeypatch, capsys, one_thread):
    """Through the CLI: exit code 2, one line naming the parameter and the step, no traceback, the
    checkpoint of step 3 kept and ``--resume`` finishing the run."""
    from retinexgs.cli import main

    real_step = torch.optim.Adam.step
    calls = [0]

    def poisoned_step(self, *a, **k):
        result = real_step(self, *a, **k)
        calls[0] += 1
        if calls[0] == 4:  # the 4th optimiser step = training step 4
            with torch.no_grad():
                self.param_groups[0]["params"][0].view(-1)[0] = float("inf")  # group 0 = the means
        return result

    monkeypatch.setattr(torch.optim.Adam, "step", poisoned_step)
    run = tmp_path / "run"
    sets = [a for s in TINY for a in ("--set", s)]
    code = main(["train", "--data", str(tiny_scene), "--out", str(run), "--config", "demo", "--quiet",
                 "--device", "cpu", *sets])
    captured = capsys.readouterr()
    assert code == 2, captured
    err = captured.err.strip()
    assert err.startswith("retinexgs train: error: Gaussian parameter means became non-finite at step 4"), err
    assert "\n" not in err and "Traceback" not in captured.err + captured.out
    assert [p.name for p in list_checkpoints(run)] == ["step_000003.pt"]
    assert not (run / "metrics.json").exists()
    monkeypatch.setattr(torch.optim.Adam, "step", real_step)
    assert main(["train", "--out", str(run), "--resume", "--quiet", "--device", "cpu"]) == 0
    assert "resuming from" in capsys.readouterr().out
    assert (run / "metrics.json").is_file()


def test_divergence_between_checks_names_the_range_and_keeps_checkpoints_clean(tiny_scene, tmp_path, one_thread):
    """Loss terms and parameters are read back only on logging, checkpoint and density steps (a host sync
    stalls the GPU queue). A NaN written into a parameter between two checks is still caught at the next check,
    before any checkpoint is written, and the message names the step it happened at (leading finite-step counts
    are kept on the device every step)."""
    run = tmp_path / "run"
    run.mkdir()
    cfg = load_config(["demo"], TINY + ["log.every=10"])  # checks at the checkpoint steps 3, 6 and at 8
    tr = Trainer(cfg, load_scene(tiny_scene), run, "cpu", progress=False, log=lambda s: None)
    checked = []
    real_check = tr.check_finite

    def counting_check(step):
        checked.append(step)
        return real_check(step)

    tr.check_finite = counting_check
    tr.train(stop_after=3)
    good = {p.name: p.read_bytes() for p in (run / "checkpoints").iterdir()}
    params = dict(tr.model.named_parameters())
    real_step = tr.optimizer.step

    def poisoned_step(*a, **k):
        result = real_step(*a, **k)
        if tr.step == 4:
            with torch.no_grad():
                params["gaussians.means"].view(-1)[0] = float("nan")
        return result

    tr.optimizer.step = poisoned_step
    # Later steps' loss terms turn NaN too (the illumination MLP sees the NaN centre): the parameter came first.
    with pytest.raises(TrainingDiverged, match=r"^Gaussian parameter means became non-finite at step 4; "
                                               r"the last good checkpoint"):
        tr.train()
    assert checked == [3, 6]
    assert {p.name: p.read_bytes() for p in (run / "checkpoints").iterdir()} == good


def test_a_non_finite_loss_between_checks_is_named_with_its_step(tiny_scene, tmp_path, one_thread):
    """A loss term that is NaN at one step between checks (and whose weight keeps the parameters finite) is
    still reported at the next check."""
    run = tmp_path / "run"
    run.mkdir()
    cfg = load_config(["demo"], TINY + ["log.every=10"])
    tr = Trainer(cfg, load_scene(tiny_scene), run, "cpu", progress=False, log=lambda s: None)
    real_loss = tr.objective.loss

    def poisoned(res, tv, step):
        terms = real_loss(res, tv, step)
        if step == 5:
            terms["sh"] = terms["sh"].detach() * float("nan")  # logged, not in the total: parameters stay finite
        return terms

    tr.objective.loss = poisoned
    with pytest.raises(TrainingDiverged, match=r"^loss term sh became non-finite at step 5; the last good"):
        tr.train()
    assert [p.name for p in list_checkpoints(run)] == ["step_000003.pt"]


def test_sigterm_stops_training_quietly_with_143_and_the_run_resumes(tiny_scene, tmp_path):
    """Issue 36: ``kill PID`` / ``timeout`` on train ends like Ctrl-C (one line, exit 143), not with glog's
    ``*** Aborted at ... SIGTERM received`` stack dump, which importing pycolmap installs (the COLMAP reader
    imports it: ``data.reader=colmap``); the checkpoints written so far stay and ``--resume`` finishes."""
    run = tmp_path / "run"
    steps = 40
    sets = [a for s in SETTINGS + [f"steps={steps}", "data.reader=colmap", "density.stop=20"]
            for a in ("--set", s)]
    proc = _start(["--data", str(tiny_scene), "--out", str(run), "--config", "demo", *sets], tmp_path / "t.log")
    try:
        t0 = time.monotonic()
        while not list_checkpoints(run) and proc.poll() is None:  # the first checkpoint is written
            assert time.monotonic() - t0 < PROCESS_TIMEOUT_S, "no checkpoint"
            time.sleep(0.02)
        assert proc.poll() is None, (tmp_path / "t.log").read_text(errors="replace")
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
    text = (tmp_path / "t.log").read_text(errors="replace")
    assert rc == 143, text
    assert "retinexgs train: terminated" in text, text
    assert "Aborted at" not in text and "@ 0x" not in text and "Traceback" not in text, text
    step = _check_run_folder(run, 2)
    assert 2 <= step < steps, text
    proc = _start(["--out", str(run), "--resume"], tmp_path / "resume.log")
    rc = _finish(proc)
    text = (tmp_path / "resume.log").read_text(errors="replace")
    assert rc == 0 and f"(step {step})" in text, text
    assert _check_run_folder(run, step) == steps
