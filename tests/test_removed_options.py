"""Run format 3 (issue 63): the options that only an ablation switched on and whose ablation lost are deleted. A run
recorded in format 2 with such a key at its old default reads as before, the key dropped silently; one that set
it otherwise is refused in one line naming the key (this code cannot reproduce it), in config.yaml and in a
checkpoint alike. The fields only those options wrote into checkpoints are dropped too."""
from __future__ import annotations

import pytest
import torch
import yaml

from retinexgs.config import plain
from retinexgs.config.versions import FORMAT, REMOVED_2_TO_3, migrate_config
from retinexgs.errors import UserError
from retinexgs.run.checkpoint import load_checkpoint
from retinexgs.run.config import load_config
from retinexgs.run.folder import read_run_config

# A value each deleted option could have been set to on purpose (what its ablation used).
NON_DEFAULT = {"model.illumination.leak": 0.01, "model.enhancement.debias_black": True,
               "model.enhancement.black_filter": 4, "loss.raw.model_error": 0.02, "density.noise_aware": True,
               "loss.rec_huber": 0.0157, "loss.rec_ssim_noise": True, "loss.rec_camera_noise": True,
               "model.enhancement.per_channel": True}


def _put(data: dict, dotted: str, value) -> None:
    *sections, key = dotted.split(".")
    for name in sections:
        data = data[name]
    data[key] = value


def _format_2(values: dict) -> dict:
    """Today's default config as format 2 wrote it: every deleted key present, with ``values`` over the defaults."""
    data = plain(load_config())
    for dotted, default in REMOVED_2_TO_3.items():
        _put(data, dotted, values.get(dotted, default))
    return {"format": 2, **data}


def test_every_deleted_key_is_gone_from_the_schema_and_the_defaults():
    assert set(NON_DEFAULT) == set(REMOVED_2_TO_3)
    for dotted in REMOVED_2_TO_3:
        with pytest.raises(UserError, match=f"unknown config key --set {dotted}"):
            load_config([], [f"{dotted}={NON_DEFAULT[dotted]}"])


def test_a_format_2_run_at_the_old_defaults_reads_as_today_s_default(tmp_path):
    data = _format_2({})
    data["scene"] = str(tmp_path)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    lines = []
    cfg, _ = read_run_config(tmp_path, lines.append)
    assert cfg == load_config() and lines == []  # dropped silently: nothing filled, nothing said


@pytest.mark.parametrize("dotted", sorted(NON_DEFAULT))
def test_a_format_2_run_that_used_a_deleted_option_is_refused_in_one_line(tmp_path, dotted):
    data = _format_2({dotted: NON_DEFAULT[dotted]})
    data["scene"] = str(tmp_path)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(UserError) as info:
        read_run_config(tmp_path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: {dotted} is {NON_DEFAULT[dotted]!r}") and "removed" in msg, msg
    assert "cannot reproduce" in msg and "\n" not in msg


def test_a_format_2_checkpoint_is_migrated_or_refused_like_its_config(tmp_path):
    density = {"grad_accum": torch.ones(2), "count": torch.ones(2), "max_radius": torch.ones(2),
               "grad_sq": torch.ones(2), "noise_sq": torch.zeros(2), "noise_count": torch.zeros(2)}
    old = tmp_path / "old.pt"
    torch.save({"format": 2, "step": 3, "model": {}, "density": dict(density), "noise_probe_rng": None,
                "config": _format_2({})}, old)
    state = load_checkpoint(old)
    assert state["format"] == FORMAT and "noise_probe_rng" not in state
    assert set(state["density"]) == {"grad_accum", "count", "max_radius"}  # only noise_aware read the others
    assert "noise_aware" not in state["config"]["density"] and "leak" not in state["config"]["model"]["illumination"]
    used = tmp_path / "used.pt"
    torch.save({"format": 2, "step": 3, "model": {}, "config": _format_2({"density.noise_aware": True})}, used)
    with pytest.raises(UserError, match=rf"^checkpoint {used}: density.noise_aware is True: that option was "
                                        r"removed from retinexgs"):
        load_checkpoint(used)


def test_a_format_0_or_1_run_goes_through_the_drop_too():
    """A run older than format 2 that lacks the deleted keys gets none of them back, and one whose format-1 raw key
    ``loss.rec_raw_model_error`` held a value moves it to loss.raw.model_error, where format 3 refuses it."""
    data = plain(load_config())
    migrated, filled = migrate_config(data, "old/config.yaml")  # format 0: no format key
    assert not any(k in filled for k in REMOVED_2_TO_3) and "noise_aware" not in migrated["density"]
    one = {**plain(load_config()), "format": 1}
    del one["loss"]["raw"]
    one["loss"]["rec_raw_model_error"] = 0.02
    with pytest.raises(UserError, match=r"^one/config.yaml: loss.raw.model_error is 0.02: "):
        migrate_config(one, "one/config.yaml")


def test_a_format_0_run_that_used_the_camera_s_noise_response_is_refused():
    """loss.rec_camera_noise was a format-0 key (FORMAT_0_VALUES filled it for runs older than it): a format-0 run
    that set it on is refused at format 3, one that lacks it is not given it back."""
    old = plain(load_config())
    old["loss"]["rec_camera_noise"] = True
    with pytest.raises(UserError, match=r"^old/config.yaml: loss.rec_camera_noise is True: that option was removed"):
        migrate_config(old, "old/config.yaml")
    migrated, filled = migrate_config(plain(load_config()), "old/config.yaml")
    assert "rec_camera_noise" not in migrated["loss"] and "loss.rec_camera_noise" not in filled


def test_the_model_predicts_one_gamma_for_all_channels():
    """model.enhancement.per_channel deleted: the EnhancementNet keeps its three outputs (checkpoints load as they
    are) and the g every tone and renderer reads is their mean, the same in each channel."""
    from retinexgs.model.retinex_model import RetinexGSModel
    from test_fused_colors import make_gaussians

    model = RetinexGSModel(make_gaussians(n=50), load_config().model, True)
    torch.manual_seed(0)
    with torch.no_grad():
        model.enhancement.out.weight.normal_(0, 0.5)  # content-dependent, different per channel
    L = torch.rand(1, 3, 24, 32)
    with torch.no_grad():
        raw, g = model.enhancement(L), model.predict_gamma(L)
    assert raw.shape[1] == 3 and float(raw.std()) > 1e-3  # the net's channels differ ...
    assert torch.allclose(g, raw.mean(dim=1, keepdim=True).expand_as(raw), rtol=0, atol=0)  # ... g is their mean
