"""Versioned runs (issue 63): ``RUN/config.yaml`` and checkpoints carry a ``format`` number; reading one applies a
migration per format step (format 0: every run written before formats, which gets the values runs had before
the keys added since), and a format newer than the code knows is refused in one line naming both numbers.
The config's choices backed by a registry above the schema (``density.kind``) are checked by the loader's table."""
from __future__ import annotations

import pytest
import torch
import yaml

from retinexgs.config import FORMAT, plain
from retinexgs.config.versions import CHECKPOINT_MIGRATIONS, CONFIG_MIGRATIONS, FORMAT_0_VALUES, RAW_KEYS_1_TO_2
from retinexgs.errors import UserError
from retinexgs.run import config as run_config
from retinexgs.run.checkpoint import load_checkpoint, save_checkpoint
from retinexgs.run.config import load_config
from retinexgs.run.folder import read_run_config, write_run_config
from scenes import run_cli


def _drop(data: dict, dotted: str) -> None:
    *sections, key = dotted.split(".")
    for name in sections:
        data = data[name]
    del data[key]


def _write(run, data: dict) -> None:
    run.mkdir(exist_ok=True)
    (run / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))


def test_one_migration_a_format_step():
    assert FORMAT == 8 and len(CONFIG_MIGRATIONS) == len(CHECKPOINT_MIGRATIONS) == FORMAT


def test_a_format_1_run_is_written_with_its_format_and_round_trips(tmp_path):
    cfg = load_config(overrides=["loss.w_tv=0.25", "density.kind=mcmc", "steps=77"])
    write_run_config(tmp_path, cfg, tmp_path)
    data = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert list(data)[0] == "format" and data["format"] == FORMAT and data["scene"] == str(tmp_path.resolve())
    lines = []
    back, scene = read_run_config(tmp_path, lines.append)
    assert back == cfg and scene == tmp_path.resolve()
    assert lines == []  # nothing filled: the run is in today's format with every key


def test_a_format_0_run_gets_the_values_runs_had_before_the_keys(tmp_path):
    """config.yaml without ``format`` (every run before today), lacking keys added since: each key of the format-0
    migration gets its old value, not today's default; a key whose default kept the behaviour gets the default;
    a whole section missing (``train``) is made with the old values inside."""
    data = plain(load_config())
    changed = [k for k, v in FORMAT_0_VALUES.items() if k.split(".")[0] != "train"]
    for key in changed:  # the format-0 values name keys as format 1 did: today's place after the 1 -> 2 move
        _drop(data, RAW_KEYS_1_TO_2.get(key, key))
    del data["train"]
    _drop(data, "loss.depth_edge")  # not in the migration: today's default is what older runs did
    data["scene"] = str(tmp_path)
    _write(tmp_path, data)
    lines = []
    cfg, _ = read_run_config(tmp_path, lines.append)
    got = plain(cfg)
    for key, old in FORMAT_0_VALUES.items():
        node = got
        for part in RAW_KEYS_1_TO_2.get(key, key).split("."):
            node = node[part]
        assert node == old, key
    assert cfg.model.enhancement.tone == "illumination" and cfg.loss.w_depth == 0.0  # not today's defaults
    assert cfg.train.momentum_batch_scaling == "none"  # inside the missing section: the old value too
    assert cfg.loss.depth_edge == load_config().loss.depth_edge
    assert cfg.train.views_pinned_gb == load_config().train.views_pinned_gb
    assert len(lines) == 1 and "predates config keys" in lines[0] and "loss.depth_edge" in lines[0]
    assert "model.enhancement.tone" in lines[0] and "train" in lines[0]
    # a run written by today's code with the same values reads back the same: the migration ran once, at format 0
    write_run_config(tmp_path, cfg, tmp_path)
    assert read_run_config(tmp_path)[0] == cfg


@pytest.mark.parametrize("fmt, expect", [
    (9, "is in run format 9, newer than this retinexgs reads (format 8)"),
    ("one", "format must be a whole number 0..8, got 'one'"),
    (-1, "format must be a whole number 0..8, got -1"),
])
def test_a_newer_or_malformed_run_format_is_refused_in_one_line(tmp_path, fmt, expect):
    write_run_config(tmp_path, load_config(), tmp_path)
    data = yaml.safe_load((tmp_path / "config.yaml").read_text())
    data["format"] = fmt
    _write(tmp_path, data)
    with pytest.raises(UserError) as info:
        read_run_config(tmp_path)
    assert expect in str(info.value) and str(tmp_path / "config.yaml") in str(info.value)
    assert "\n" not in str(info.value)


def test_eval_of_a_run_from_a_newer_version_is_one_line(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    write_run_config(run, load_config(), tmp_path)
    data = yaml.safe_load((run / "config.yaml").read_text())
    data["format"] = FORMAT + 1
    _write(run, data)
    save_checkpoint(run, 1, {"step": 1, "model": {}})
    code, out, err = run_cli(["eval", "--run", run, "--device", "cpu"], capsys)
    assert code == 2, (code, out, err)
    assert f"run format {FORMAT + 1}" in err and f"(format {FORMAT})" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err


def test_checkpoints_carry_the_format_and_older_ones_are_migrated(tmp_path):
    path = save_checkpoint(tmp_path, 1, {"step": 1, "model": {"w": torch.ones(2)}, "train_seconds": 5.0})
    assert torch.load(path, weights_only=False)["format"] == FORMAT
    state = load_checkpoint(path)
    assert state["train_seconds"] == 5.0 and state["format"] == FORMAT
    # format 0: no format, none of the fields added since, and a config that lacks keys added since
    old_cfg = plain(load_config())
    _drop(old_cfg, "model.near_fraction")
    old = tmp_path / "old.pt"
    torch.save({"step": 3, "model": {"w": torch.ones(2)}, "config": old_cfg}, old)
    state = load_checkpoint(old)
    assert (state["train_seconds"], state["order"], state["density"], state["train_views"]) == (0.0, [], {}, None)
    assert state["format"] == FORMAT and state["config"]["model"]["near_fraction"] == 0.0
    assert "format" not in state["config"]
    newer = tmp_path / "newer.pt"
    torch.save({"format": FORMAT + 1, "step": 3, "model": {}}, newer)
    with pytest.raises(UserError, match=rf"checkpoint {newer} is in run format {FORMAT + 1}, newer than this "
                                        rf"retinexgs reads \(format {FORMAT}\)"):
        load_checkpoint(newer)


def test_registry_choices_are_checked_by_the_loader_in_one_line(monkeypatch):
    """``density.kind`` is a plain string in the schema (the strategies sit above it); the loader's table checks
    it, with the source named, once even when the value is not a string; a new row checks another key."""
    with pytest.raises(UserError) as info:
        load_config([], ["density.kind=nope"])
    assert str(info.value) == "--set density.kind=nope: density.kind must be one of default, mcmc, got 'nope'"
    with pytest.raises(UserError) as info:
        load_config([], ["density.kind=3"])
    assert str(info.value) == "--set density.kind=3: density.kind must be one of default, mcmc, got 3"
    monkeypatch.setitem(run_config.CHOICES, ("model", "background"), lambda: ["black"])
    assert load_config([], ["model.background=black"]).model.background == "black"
    with pytest.raises(UserError, match=r"^--set model.background=mean: model.background must be one of black, "
                                        r"got 'mean'$"):
        load_config([], ["model.background=mean"])


def test_a_format_4_run_keeps_the_paper_reflectance_prior_on_raw_scenes():
    """Format 4 -> 5: a run made before loss.raw.r_prior_luma trained the R prior on R̂'s luma too (κ = 1); a value
    written on purpose is kept; today's default is the chroma alone."""
    from retinexgs.config.versions import migrate_config
    old, filled = migrate_config({"format": 4, "loss": {"raw": {"mode": "noise"}}}, "old/config.yaml")
    assert old["loss"]["raw"]["r_prior_luma"] == 1.0 and "loss.raw.r_prior_luma" in filled
    kept, _ = migrate_config({"format": 4, "loss": {"raw": {"r_prior_luma": 0.5}}}, "old/config.yaml")
    assert kept["loss"]["raw"]["r_prior_luma"] == 0.5
    assert load_config().loss.raw.r_prior_luma == 0.0


def test_a_format_5_run_reads_its_binned_views_with_the_one_kappa_it_had():
    """Format 5 -> 6: before loss.raw.r_prior_luma_binned, views binned by data.downscale read the R prior with
    loss.raw.r_prior_luma; the new key takes that value (the run resumes as it trained); today's default is 1."""
    from retinexgs.config.versions import migrate_config
    for kappa in (0.0, 0.5, 1.0):
        old, filled = migrate_config({"format": 5, "loss": {"raw": {"r_prior_luma": kappa}}}, "old/config.yaml")
        assert old["loss"]["raw"]["r_prior_luma_binned"] == kappa and "loss.raw.r_prior_luma_binned" in filled
    four, _ = migrate_config({"format": 4, "data": {"downscale": 2}}, "old/config.yaml")  # before κ at all: 1
    assert four["loss"]["raw"]["r_prior_luma_binned"] == 1.0
    kept, _ = migrate_config({"format": 5, "loss": {"raw": {"r_prior_luma": 0.0, "r_prior_luma_binned": 0.3}}},
                             "old/config.yaml")
    assert kept["loss"]["raw"]["r_prior_luma_binned"] == 0.3
    assert load_config().loss.raw.r_prior_luma_binned == 1.0


def test_a_format_6_run_keeps_training_at_the_resolution_it_had():
    """Format 6 -> 7: before the coarse-to-fine default a run without train.resolution trained at full size, and a
    run with a schedule pooled every view by its stage's k (no pixel floor): both resume as they trained."""
    from retinexgs.config.versions import migrate_config
    old, filled = migrate_config({"format": 6, "steps": 50}, "old/config.yaml")
    assert old["train"]["resolution"] == [] and old["train"]["resolution_min_pixels"] == 0
    assert {"train.resolution", "train.resolution_min_pixels"} <= set(filled)
    kept, _ = migrate_config({"format": 6, "train": {"resolution": [[0.2, 4]]}}, "old/config.yaml")
    assert kept["train"]["resolution"] == [[0.2, 4]] and kept["train"]["resolution_min_pixels"] == 0
    today = load_config().train
    assert today.resolution == [(0.8, 4), (0.95, 2)] and today.resolution_min_pixels == 6_000_000


def test_a_format_7_run_keeps_its_priors_weights_to_the_end():
    """Runs before loss.prior_late_views kept w_r, w_l throughout; today's default lowers them late."""
    from retinexgs.config.versions import migrate_config
    old, filled = migrate_config({"format": 7, "steps": 50}, "old/config.yaml")
    assert old["loss"]["prior_late_views"] == 0 and "loss.prior_late_views" in filled
    kept, _ = migrate_config({"format": 7, "loss": {"prior_late_views": 4}}, "old/config.yaml")
    assert kept["loss"]["prior_late_views"] == 4
    assert load_config([]).loss.prior_late_views == 9
