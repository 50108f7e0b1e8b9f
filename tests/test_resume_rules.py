"""Resume rules (issue 15): --set/--config on --resume are applied and recorded in the run's config.yaml, or
refused by name; --data is checked against the run's scene (--relocate-scene for a moved one); one trainer
per run folder (a lock); --out that cannot hold a run is refused before the scene is loaded."""
import fcntl
import json
import os
import shutil
from pathlib import Path

import pytest
import torch
import yaml

from retinexgs.cli import main
from retinexgs.config.versions import FORMAT
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.errors import UserError
from retinexgs.train import runner as run_module
from retinexgs.run.checkpoint import latest_checkpoint
from retinexgs.run.config import load_config
from retinexgs.train.resume import run_lock
from retinexgs.train.runner import train_run
from retinexgs.train.trainer import Trainer
from scenes import TINY_RUN, tiny_trained_run

TINY = TINY_RUN
T = ["--device", "cpu", "--quiet"]


@pytest.fixture(scope="module")
def originals(tmp_path_factory):
    """A tiny scene and a run of it trained for 3 steps."""
    return tiny_trained_run(tmp_path_factory.mktemp("originals"))


@pytest.fixture
def run(originals, tmp_path, one_thread):
    """A copy of the trained run (pointing at the shared scene)."""
    dst = tmp_path / "run"
    shutil.copytree(originals[1], dst)
    return dst


def recorded(run: Path) -> dict:
    return yaml.safe_load((run / "config.yaml").read_text())


def cli(argv, capsys):
    code = main(argv)
    out = capsys.readouterr()
    assert "Traceback" not in out.out + out.err
    return code, out.out, out.err.strip()


@pytest.fixture
def no_scene_load(monkeypatch):
    """Fails the test if the scene is loaded (the refusals must come first)."""
    def refuse(*a, **k):
        raise AssertionError("the scene was loaded before the refusal")
    monkeypatch.setattr(run_module, "open_scene", refuse)


# ---- --set / --config on --resume --------------------------------------------------------------------------

def test_resume_set_steps_is_recorded_before_training(run, capsys, monkeypatch):
    """`--resume --set steps=6`, killed while training, then `--resume`: trains to 6 (the issue: it said
    'already finished its 3 steps' because config.yaml kept steps=3)."""
    def killed(self, *a, **k):
        raise KeyboardInterrupt  # the process dies mid-training, after the settings were recorded

    monkeypatch.setattr(Trainer, "train", killed)
    code, out, err = cli(["train", "--out", str(run), "--resume", "--set", "steps=6", *T], capsys)
    assert code != 0 and "interrupted" in err
    assert recorded(run)["steps"] == 6
    monkeypatch.undo()
    code, out, err = cli(["train", "--out", str(run), "--resume", *T], capsys)
    assert code == 0, err
    assert "already finished" not in out
    assert latest_checkpoint(run).name == "step_000006.pt"


def test_resume_config_file_is_applied_and_recorded(run, capsys):
    assert recorded(run)["loss"]["w_tv"] > 0
    code, out, err = cli(["train", "--out", str(run), "--resume", "--config", "ablations/no_tv", "--set", "steps=4",
                          *T], capsys)
    assert code == 0, err
    data = recorded(run)
    assert data["loss"]["w_tv"] == 0 and data["steps"] == 4
    assert "--resume: loss.w_tv" in out and "recorded in" in out
    assert latest_checkpoint(run).name == "step_000004.pt"


def test_resume_applies_new_learning_rates_to_the_optimizer(run, originals):
    """The optimiser state comes from the checkpoint, but its learning rates from the (changed) config."""
    from retinexgs.data import load_scene

    cfg = load_config(["demo"], TINY + ["lr.quats=0.123", "lr.illumination=0.0042"])
    tr = Trainer(cfg, load_scene(originals[0]), run, "cpu", resume=True, progress=False, log=lambda s: None)
    rates = {g["name"]: g["lr"] for g in tr.optimizer.param_groups}
    assert rates["quats"] == 0.123 and rates["illumination"] == 0.0042


@pytest.mark.parametrize("argv, key", [
    (["--set", "method=3dgs"], "method"),
    (["--config", "ablations/baseline_3dgs"], "method"),
    (["--set", "model.sh_degree=2"], "model.sh_degree"),
    (["--set", "model.illumination.hidden=8"], "model.illumination.hidden"),
    (["--set", "decomposer.method=lr3m"], "decomposer.method"),
    (["--set", "decomposer.params={cg_max_iter: 50}"], "decomposer.params"),
    (["--set", "data.downscale=2"], "data.downscale"),
    (["--set", "seed=5"], "seed"),
])
def test_resume_refuses_structural_changes_by_name(run, capsys, no_scene_load, argv, key):
    before = (run / "config.yaml").read_bytes()
    code, out, err = cli(["train", "--out", str(run), "--resume", *argv, *T], capsys)
    assert code == 2
    assert err.startswith(f"retinexgs train: error: --resume cannot change {key}"), err
    assert "start a new run" in err and "\n" not in err
    assert (run / "config.yaml").read_bytes() == before


def test_resume_refuses_steps_below_the_trained_step(run, capsys, no_scene_load):
    code, out, err = cli(["train", "--out", str(run), "--resume", "--set", "steps=2", *T], capsys)
    assert code == 2 and "steps=2 is below the step the run" in err and "(3)" in err
    assert recorded(run)["steps"] == 3


def test_resume_bad_value_is_named(run, capsys, no_scene_load):
    code, out, err = cli(["train", "--out", str(run), "--resume", "--set", "lr.means=fast", *T], capsys)
    assert code == 2 and "--set lr.means=fast: lr.means must be a number > 0, got 'fast'" in err


def test_plain_resume_leaves_config_untouched(run, capsys):
    before = (run / "config.yaml").read_bytes()
    code, out, err = cli(["train", "--out", str(run), "--resume", "--set", "steps=3", *T], capsys)  # no change
    assert code == 0 and "already finished its 3 steps" in out, err
    assert (run / "config.yaml").read_bytes() == before


# ---- --data on --resume ------------------------------------------------------------------------------------

def test_resume_with_the_same_scene_is_fine(run, originals, capsys):
    code, out, err = cli(["train", "--out", str(run), "--resume", "--data", str(originals[0]), *T], capsys)
    assert code == 0, err


def test_resume_with_another_scene_is_refused_naming_both(run, originals, tmp_path, capsys, no_scene_load):
    other = tmp_path / "other"
    shutil.copytree(originals[0], other)
    code, out, err = cli(["train", "--out", str(run), "--resume", "--data", str(other), *T], capsys)
    assert code == 2 and f"--data {other} is not the scene" in err and str(originals[0]) in err
    assert "--relocate-scene" in err


def test_relocate_scene_points_the_run_at_the_moved_folder(run, originals, tmp_path, capsys):
    moved = tmp_path / "moved"
    shutil.copytree(originals[0], moved)
    code, out, err = cli(["train", "--out", str(run), "--resume", "--data", str(moved), "--relocate-scene",
                          "--set", "steps=4", *T], capsys)
    assert code == 0, err
    assert recorded(run)["scene"] == str(moved.resolve()) and recorded(run)["steps"] == 4
    # from now on the run reads the moved scene without --data
    code, out, err = cli(["train", "--out", str(run), "--resume", "--data", str(moved), *T], capsys)
    assert code == 0, err


def test_resume_of_a_moved_scene_says_how_to_relocate(run, originals, tmp_path, capsys):
    data = recorded(run)
    data["scene"] = str(tmp_path / "gone")
    (run / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    code, out, err = cli(["train", "--out", str(run), "--resume", *T], capsys)
    assert code == 2 and f"{tmp_path / 'gone'}, does not exist" in err and "--relocate-scene" in err
    code, out, err = cli(["train", "--out", str(run), "--resume", "--data", str(originals[0]), "--relocate-scene",
                          *T], capsys)
    assert code == 0, err
    assert recorded(run)["scene"] == str(Path(originals[0]).resolve())


def test_relocate_scene_refuses_a_scene_with_other_views(run, originals, tmp_path, capsys):
    other = make_demo_scene(tmp_path / "other", n_train=4, n_test=1, width=24, height=18, n_points=200)
    before = (run / "config.yaml").read_bytes()
    code, out, err = cli(["train", "--out", str(run), "--resume", "--data", str(other), "--relocate-scene", *T],
                         capsys)
    assert code == 2 and "--relocate-scene" in err and "4 training views" in err and "trained on 3" in err, err
    assert (run / "config.yaml").read_bytes() == before


def test_relocate_scene_needs_resume_and_data(run, originals, tmp_path, capsys):
    code, out, err = cli(["train", "--out", str(tmp_path / "new"), "--data", str(originals[0]), "--relocate-scene",
                          *T], capsys)
    assert code == 2 and "--relocate-scene applies only with --resume" in err
    code, out, err = cli(["train", "--out", str(run), "--resume", "--relocate-scene", *T], capsys)
    assert code == 2 and "--relocate-scene needs --data" in err
    assert not (tmp_path / "new").exists()


# ---- one trainer per run folder ----------------------------------------------------------------------------

def test_a_second_trainer_on_a_run_is_refused(run, capsys, no_scene_load):
    fd = os.open(run, os.O_RDONLY)  # what a running trainer holds
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        code, out, err = cli(["train", "--out", str(run), "--resume", "--set", "steps=5", *T], capsys)
    finally:
        os.close(fd)
    assert code == 2 and f"run folder {run} is in use by another trainer" in err
    assert recorded(run)["steps"] == 3


def test_the_lock_is_held_while_training_and_released_after(run, originals, monkeypatch):
    seen = []

    def train(self, *a, **k):  # a second trainer while this one trains
        with pytest.raises(UserError, match="in use by another trainer"):
            with run_lock(run):
                pass
        seen.append(True)
        return {"seconds": 0.0}

    monkeypatch.setattr(Trainer, "train", train)
    train_run(None, run, (), ["steps=4"], "cpu", resume=True, progress=False, log=lambda s: None)
    assert seen == [True]
    with run_lock(run):  # released
        pass


def test_a_new_run_checks_the_lock_and_emptiness_when_it_makes_its_folder(originals, tmp_path, monkeypatch,
                                                                           one_thread):
    """Two new runs on one --out: the one that loads second is refused when it makes the folder."""
    real = run_module.Trainer
    held = []

    def other_trainer_first(cfg, scene, run_dir, *a, **k):
        tr = real(cfg, scene, run_dir, *a, **k)
        run_dir.mkdir(parents=True)
        fd = os.open(run_dir, os.O_RDONLY)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # the other trainer, still running
        held.append(fd)
        return tr

    monkeypatch.setattr(run_module, "Trainer", other_trainer_first)
    out = tmp_path / "run"
    try:
        with pytest.raises(UserError, match=f"run folder {out} is in use by another trainer"):
            train_run(originals[0], out, ["demo"], TINY, "cpu", progress=False, log=lambda s: None)
    finally:
        os.close(held.pop())
    assert list(out.iterdir()) == []

    def other_trainer_finished(cfg, scene, run_dir, *a, **k):
        tr = real(cfg, scene, run_dir, *a, **k)
        (run_dir / "config.yaml").write_text("the other run's\n")
        return tr

    monkeypatch.setattr(run_module, "Trainer", other_trainer_finished)
    with pytest.raises(UserError, match="was filled by another trainer meanwhile"):
        train_run(originals[0], out, ["demo"], TINY, "cpu", progress=False, log=lambda s: None)
    assert (out / "config.yaml").read_text() == "the other run's\n"


# ---- --out that cannot hold a run --------------------------------------------------------------------------

def test_out_is_a_file(originals, tmp_path, capsys, no_scene_load):
    f = tmp_path / "afile"
    f.write_text("mine")
    code, out, err = cli(["train", "--data", str(originals[0]), "--out", str(f), *T], capsys)
    assert code == 2 and f"--out {f} is a file" in err
    assert f.read_text() == "mine"


def test_out_under_a_file(originals, tmp_path, capsys, no_scene_load):
    f = tmp_path / "afile"
    f.write_text("mine")
    code, out, err = cli(["train", "--data", str(originals[0]), "--out", str(f / "sub" / "run"), *T], capsys)
    assert code == 2 and f"lies under {f}, which is a file" in err


def test_out_not_writable(originals, tmp_path, capsys, no_scene_load, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    os.chmod(ro, 0o500)
    if os.geteuid() == 0:  # root writes anywhere: make the write fail as it would for a user
        import tempfile

        real = tempfile.mkstemp

        def mkstemp(*a, dir=None, **k):
            if dir is not None and Path(dir) == ro:
                raise PermissionError(13, "Permission denied")
            return real(*a, dir=dir, **k)

        monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
    try:
        code, out, err = cli(["train", "--data", str(originals[0]), "--out", str(ro / "run"), *T], capsys)
    finally:
        os.chmod(ro, 0o700)
    assert code == 2 and f"--out {ro / 'run'}: cannot write in {ro} (Permission denied)" in err, err
    assert list(ro.iterdir()) == []


def test_a_run_older_than_a_key_gets_the_behaviour_it_was_trained_with(run):
    """A config.yaml without keys added later is filled from default.yaml, except keys whose default changed since
    they were added (its format's migration, retinexgs/config/versions.py): a run from before
    ``model.enhancement.tone`` was trained with the gamma on L̂, so it must render that way, not with today's
    default tone."""
    from retinexgs.run.folder import read_run_config
    raw = recorded(run)
    assert raw.pop("format") == FORMAT  # a run made today records its format; one without is format 0 (before formats)
    assert raw["model"]["enhancement"]["tone"] == "exposure"  # a run made today records it
    assert raw["loss"]["w_depth"] == 0.3
    assert raw["loss"]["rec_domain"] == "exposed_ssim"
    assert raw["model"]["background"] == "mean"
    assert raw["model"]["enhancement"]["shoulder"] == 0.5
    del raw["model"]["background"]
    del raw["model"]["enhancement"]["shoulder"]
    del raw["model"]["enhancement"]["tone"]
    del raw["model"]["enhancement"]["per_view"]
    del raw["loss"]["w_depth"]
    del raw["loss"]["depth_edge"]
    del raw["loss"]["rec_domain"]
    assert raw["loss"]["exp_highlight_share"] == 0.05 and raw["train"]["momentum_batch_scaling"] == "power"
    assert raw["train"]["views_pinned_gb"] == 4.0
    del raw["loss"]["exp_highlight_share"]
    del raw["train"]["momentum_batch_scaling"]
    del raw["train"]["views_pinned_gb"]
    (run / "config.yaml").write_text(yaml.safe_dump(raw))
    lines = []
    cfg, _ = read_run_config(run, lines.append)
    assert cfg.model.enhancement.tone == "illumination"
    assert cfg.loss.w_depth == 0.0  # trained without the depth prior
    assert cfg.model.enhancement.per_view is True  # unchanged default: filled from default.yaml
    assert cfg.loss.depth_edge == 10.0
    assert cfg.loss.rec_domain == "photo"  # trained with the reconstruction term on the dark values
    assert cfg.model.background == "black"  # rendered over black: no background buffer in its checkpoints
    assert cfg.model.enhancement.shoulder == 1.0  # its highlights clipped
    assert cfg.loss.exp_highlight_share == 0.0  # metered by the average alone
    assert cfg.train.momentum_batch_scaling == "none"  # torch's betas whatever the batch
    assert cfg.train.views_pinned_gb == 4.0  # no effect on the numbers: today's default
    for key in ("model.enhancement.tone", "model.enhancement.per_view", "loss.w_depth", "loss.depth_edge",
                "loss.rec_domain", "model.background", "model.enhancement.shoulder",
                "loss.exp_highlight_share", "train.momentum_batch_scaling", "train.views_pinned_gb"):
        assert key in lines[0]


@pytest.mark.parametrize("argv", [["eval"], ["render"], ["export", "--out", "OUT/fox.ply"]])
def test_a_run_whose_scene_moved_says_how_to_relocate_it(run, tmp_path, capsys, argv):
    """eval, render and export of a run whose scene folder is gone name the folder and the --relocate-scene fix."""
    data = recorded(run)
    data["scene"] = str(tmp_path / "gone")
    (run / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    argv = [a.replace("OUT", str(tmp_path)) for a in argv]
    code, out, err = cli([argv[0], "--run", str(run), *argv[1:], "--device", "cpu"], capsys)
    assert code == 2, err
    assert str(tmp_path / "gone") in err and "--resume --data NEW_SCENE --relocate-scene" in err, err


def test_train_seconds_add_up_over_resumed_sessions(originals, tmp_path, capsys, one_thread):
    """A resumed run reports the training time of all its sessions, not only the last one (issue 36)."""
    run = tmp_path / "run"
    logs = []
    train_run(originals[0], run, ["demo"], TINY + ["steps=4"], "cpu", progress=False, log=logs.append)
    state = torch.load(latest_checkpoint(run), weights_only=False)
    first = state["train_seconds"]
    assert first > 0
    # Pretend the first session took 1000 s: the resumed run's total must include it.
    state["train_seconds"] = 1000.0
    torch.save(state, latest_checkpoint(run))
    logs.clear()
    metrics = train_run(None, run, [], ["steps=6"], "cpu", resume=True, progress=False, log=logs.append)
    took = [m for m in logs if m.startswith("trained 6 steps")]
    assert took and "in all" in took[0] and "this session" in took[0], logs
    total = json.loads((run / "metrics.json").read_text())["train"]["train_seconds"]
    assert 1000.0 <= total < 1000.0 + 600, total  # the first session's 1000 s are counted
    assert torch.load(latest_checkpoint(run), weights_only=False)["train_seconds"] >= 1000.0
    records = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    assert records[-1]["seconds"] >= 1000.0
