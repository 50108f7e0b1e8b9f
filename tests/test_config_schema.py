"""One typed schema for the config (issue 15): every shipped config validates; a bad value is refused before
any work starts, naming where it came from, the key path, the value and what was expected."""

import pytest
import yaml

from retinexgs.cli import main
from retinexgs.errors import UserError
from retinexgs.config import configs_dir, plain, read_yaml
from retinexgs.config.schema import ConfigSchema
from retinexgs.run.config import load_config, validate

SHIPPED = sorted(p for p in configs_dir().rglob("*.yaml"))


def test_configs_are_found():
    assert configs_dir() / "default.yaml" in SHIPPED and len(SHIPPED) > 5


@pytest.mark.parametrize("path", SHIPPED, ids=[str(p.relative_to(configs_dir())) for p in SHIPPED])
def test_every_shipped_config_validates(path):
    """default.yaml itself, and every other file as an override of it: a key without a schema field (or a
    schema field missing from default.yaml) fails here at once."""
    files = [] if path.name == "default.yaml" and path.parent == configs_dir() else [str(path)]
    cfg = load_config(files)
    assert set(plain(cfg)) == set(ConfigSchema.model_fields)


def test_every_default_key_is_in_the_schema_and_back():
    def keys(d, prefix=""):
        out = set()
        for k, v in d.items():
            if isinstance(v, dict) and k != "params":
                out |= keys(v, f"{prefix}{k}.")
            else:
                out.add(prefix + k)
        return out

    default = read_yaml(configs_dir() / "default.yaml")
    assert keys(default) == keys(plain(load_config()))


def test_load_config_returns_typed_validated_data():
    cfg = load_config(overrides=["loss.w_tv=0", "lr.means=1e-4", "decomposer.params={iterations: 3, beta: 1}"])
    assert type(cfg) is ConfigSchema and cfg.loss.w_tv == 0.0
    data = plain(cfg)  # what a run records in config.yaml and a checkpoint
    assert type(data) is dict and type(data["loss"]) is dict and type(data["model"]["illumination"]) is dict
    assert yaml.safe_load(yaml.safe_dump(data)) == data
    assert cfg.loss.w_tv == 0.0 and isinstance(cfg.loss.w_tv, float)
    assert cfg.lr.means == 1e-4  # PyYAML reads 1e-4 as a string: a string spelling a number is that number
    assert cfg.decomposer.params == {"iterations": 3, "beta": 1.0}  # checked per method, typed as its schema says


@pytest.mark.parametrize("setting, expect", [
    # the cases
    ("model.sh_degree=abc", "--set model.sh_degree=abc: model.sh_degree must be an integer 0..3, got 'abc'"),
    ("lr.means=fast", "--set lr.means=fast: lr.means must be a number > 0, got 'fast'"),
    ("loss=3", "--set loss=3: loss must be a mapping with the keys lambda_ssim, w_r, "),
    ("data.downscale=half", "--set data.downscale=half: data.downscale must be a number >= 1, got 'half'"),
    # types are strict, ranges and choices checked
    ("model.sh_degree=4", "model.sh_degree must be an integer 0..3, got 4"),
    ("model.sh_degree=2.0", "model.sh_degree must be an integer 0..3, got 2.0"),
    ("model.sh_degree=true", "model.sh_degree must be an integer 0..3, got True"),
    ("steps=-3", "steps must be a positive integer, got -3"),
    ("steps='100'", "steps must be a positive integer, got '100'"),
    ("loss.w_tv=-1", "loss.w_tv must be a number >= 0, got -1"),
    ("loss.w_tv=yes", "loss.w_tv must be a number >= 0, got True"),
    ("loss.enhance_trains_scene=1", "loss.enhance_trains_scene must be true or false, got 1"),
    ("method=magic", "method must be one of retinexgs, 3dgs, pre, post, got 'magic'"),
    ("data.reader=json", "data.reader must be one of auto, transforms, colmap, sfm, got 'json'"),
    ("decomposer.method=retinex", "decomposer.method must be one of lr3m, lime, none"),
    ("decomposer.params=3", "decomposer.params must be a mapping of the decomposer's parameters, got 3"),
    ("data.cache_dir=5", "data.cache_dir must be a string or null, got 5"),
    ("data.white_balance=sepia", "data.white_balance must be one of as-shot, grey-edge, got 'sepia'"),
    ("loss.raw.unit=stops", "loss.raw.unit must be one of plain, sigma, got 'stops'"),
    ("loss.raw.prior_snr=-1", "loss.raw.prior_snr must be a number >= 0, got -1"),
    ("model.illumination.hidden=0", "model.illumination.hidden must be an integer >= 1, got 0"),
    ("model.illumination=[1]", "model.illumination must be a mapping with the keys pos_freqs"),
    ("model.enhancement.gamma_range=[1, 0.5]",
     "--set model.enhancement.gamma_range=[1, 0.5]: model.enhancement.gamma_range must be [low, high] with low < high"),
    ("model.enhancement.gamma_range=[0.1]", "model.enhancement.gamma_range must be a list [low, high]"),
    ("density.prune_opacity=2", "density.prune_opacity must be a number 0..1, got 2"),
    ("checkpoint.keep=0", "checkpoint.keep must be an integer >= 1, got 0"),
    ("eval=null", "eval must be a mapping with the keys lpips, sheet_max_side, got None"),
])
def test_bad_values_name_the_source_key_value_and_type(setting, expect):
    with pytest.raises(UserError) as info:
        load_config(overrides=[setting])
    assert expect in str(info.value)


def test_exposed_reconstruction_needs_the_scene_reference():
    with pytest.raises(UserError) as info:
        load_config(["paper"], overrides=["loss.rec_domain=exposed_ssim"])  # the paper has no L_ref
    assert "loss.rec_domain 'exposed_ssim' exposes the photo by 1 / lin(L_ref)" in str(info.value)
    assert load_config(overrides=["loss.rec_domain=exposed"]).loss.rec_domain == "exposed"
    with pytest.raises(UserError, match="loss.rec_domain must be one of photo, exposed, exposed_ssim"):
        load_config(overrides=["loss.rec_domain=linear"])


def test_a_bad_value_in_a_config_file_names_the_file(tmp_path):
    f = tmp_path / "mine.yaml"
    f.write_text("model:\n  sh_degree: 7\n")
    with pytest.raises(UserError, match=rf"config {f}: model.sh_degree must be an integer 0..3, got 7"):
        load_config([str(f)])


def test_unknown_keys_are_refused_everywhere(tmp_path):
    with pytest.raises(UserError, match=r"unknown config key --set loss\.w_typo \(known"):
        load_config(overrides=["loss.w_typo=1"])
    f = tmp_path / "extra.yaml"
    f.write_text("model:\n  illumination:\n    width: 3\n")
    with pytest.raises(UserError, match="unknown config key"):
        load_config([str(f)])
    # a base config (a run's config.yaml, or default.yaml with a key the schema lacks)
    base = plain(load_config())
    base["loss"]["w_new"] = 1.0
    with pytest.raises(UserError, match=r"base.yaml: unknown config key loss.w_new \(not in the config schema"):
        validate(base, base_label="base.yaml")


def test_a_missing_key_is_named():
    base = plain(load_config())
    del base["density"]["every"]
    with pytest.raises(UserError, match="config key density.every is missing"):
        validate(base)


def test_cli_refuses_a_bad_value_before_loading_the_scene_or_writing(tmp_path, capsys):
    """The config is checked first: the scene does not even exist here, and nothing is written."""
    for setting, expect in [("model.sh_degree=abc", "model.sh_degree must be an integer 0..3, got 'abc'"),
                            ("loss=3", "loss must be a mapping"), ("lr.means=fast", "lr.means must be a number"),
                            ("data.downscale=half", "data.downscale must be a number >= 1, got 'half'")]:
        code = main(["train", "--data", str(tmp_path / "no_scene"), "--out", str(tmp_path / "run"), "--quiet",
                     "--device", "cpu", "--set", setting])
        err = capsys.readouterr().err
        assert code == 2 and f"--set {setting}: {expect}" in err and "Traceback" not in err, err
        assert "\n" not in err.strip()
    assert list(tmp_path.iterdir()) == []
