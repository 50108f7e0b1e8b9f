"""One typed config from the loader to the kernels (issue #51): the package reads config keys as attributes of
the validated :class:`retinexgs.config.schema.Config`, never by string and never with a fallback of its own, so a
key's default lives in configs/default.yaml alone (and, for run folders older than the key, in the migration of
their format, ``retinexgs.config.versions``). The config has no mapping methods at all (issue 63): tests and
scripts read attributes too."""
from __future__ import annotations

import ast
import re
from pathlib import Path
from typing import List, Optional, Set

import pytest
import torch
import yaml

import retinexgs
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.config import configs_dir, plain
from retinexgs.config.schema import Config, Section
from retinexgs.run.config import load_config

PACKAGE = Path(retinexgs.__file__).resolve().parent

# The loader and the schema work on plain YAML data by design (merge, predating fill, resume's key-by-key
# comparison); everything else receives the typed object.
LOADER = {"run/config.py", "config/schema.py", "config/files.py", "config/versions.py"}

# The heuristic, stated: a name is "a config" when it is spelt like one (``cfg``, ``config``, ``*_cfg``,
# ``*cfg`` such as ``dcfg``, as a variable or an attribute like ``self.cfg``), when it is a parameter annotated
# with a schema class (``c: Loss``), or when it is assigned from an attribute chain that starts at a config
# (``c = self.cfg.loss``). A subscript with a string constant (``cfg["loss"]``, ``c["w_tv"]``) or a
# ``.get("key"...)`` call on such a chain is a read by string. ``decomposer.params`` is free-form per method (a
# plain dict, checked by ``check_decomposer_params``): a chain that passes through ``.params`` is not a config.
CONFIG_NAME = re.compile(r"^(cfg|config|\w*cfg|\w*_config)$")
# Calls that return a config: ``load_config(...)["loss"]`` is a read by string too.
CONFIG_CALLS = {"load_config", "validate", "read_run_config", "load_run", "variant_config"}
SCHEMA_CLASSES = {name for name, obj in vars(__import__("retinexgs.config.schema", fromlist=["x"])).items()
                  if isinstance(obj, type) and issubclass(obj, Section)} | {"Config"}


def _chain(node: ast.AST) -> Optional[List[str]]:
    """``self.cfg.loss`` -> ["self", "cfg", "loss"]; subscripts are stepped through; None for other roots."""
    parts: List[str] = []
    while True:
        if isinstance(node, ast.Attribute):
            parts.append(node.attr)
            node = node.value
        elif isinstance(node, ast.Subscript):
            node = node.value
        elif isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            if name not in CONFIG_CALLS:
                return None
            parts.append("cfg")  # a config, whatever the name it would be given
            return parts[::-1]
        elif isinstance(node, ast.Name):
            parts.append(node.id)
            return parts[::-1]
        else:
            return None


def _is_config(node: ast.AST, bound: Set[str]) -> bool:
    parts = _chain(node)
    if not parts or "params" in parts:
        return False
    return parts[0] in bound or any(CONFIG_NAME.match(p) for p in parts)


def _annotation_names(ann: Optional[ast.AST]) -> Set[str]:
    if ann is None:
        return set()
    if isinstance(ann, ast.Constant) and isinstance(ann.value, str):  # a string annotation
        try:
            ann = ast.parse(ann.value, mode="eval").body
        except SyntaxError:
            return set()
    return {n.id for n in ast.walk(ann) if isinstance(n, ast.Name)} | \
        {n.attr for n in ast.walk(ann) if isinstance(n, ast.Attribute)}


def string_reads(source: str, filename: str = "<src>") -> List[str]:
    """``line: text`` of every read of a config key by string in ``source`` (the heuristic above)."""
    tree = ast.parse(source, filename)
    found: List[str] = []
    scopes = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Module))]
    for scope in scopes:
        bound: Set[str] = set()
        if not isinstance(scope, ast.Module):
            args = scope.args.posonlyargs + scope.args.args + scope.args.kwonlyargs
            bound |= {a.arg for a in args if _annotation_names(a.annotation) & SCHEMA_CLASSES}
        body = list(ast.walk(scope))
        for _ in range(2):  # assignments of assignments (c = cfg.loss; d = c ...)
            for n in body:
                if isinstance(n, ast.Assign) and _is_config(n.value, bound):
                    bound |= {t.id for t in n.targets if isinstance(t, ast.Name)}
        for n in body:
            if isinstance(n, ast.Subscript) and isinstance(n.slice, ast.Constant) \
                    and isinstance(n.slice.value, str) and _is_config(n.value, bound):
                found.append(f"{n.lineno}: {ast.get_source_segment(source, n)}")
            elif isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "get" \
                    and n.args and isinstance(n.args[0], ast.Constant) and isinstance(n.args[0].value, str) \
                    and _is_config(n.func.value, bound):
                found.append(f"{n.lineno}: {ast.get_source_segment(source, n)}")
    return sorted(set(found), key=lambda s: (int(s.split(":")[0]), s))


def test_the_heuristic_finds_reads_by_string():
    src = '''
def f(cfg, state, c2: "Loss", x: int):
    a = cfg["loss"]["w_tv"]
    c = cfg.loss
    b = c["w_tv"] + c.get("w_sh", 0.0) + c2["w_r"]
    d = self.cfg.get("steps")
    e = tcfg["views_per_rank"]
    loss = load_config([])["loss"]
    share = loss["rec_noise_share"] + other(cfg)["x"]
    p = cfg.decomposer.params["beta"] + cfg.decomposer.params.get("beta", 1)
    return state["step"], x, cfg.loss.w_tv, dict(a=1)["a"]
'''
    hits = {h.split(": ", 1)[1] for h in string_reads(src)}
    assert hits == {'cfg["loss"]', 'cfg["loss"]["w_tv"]', 'c["w_tv"]', 'c.get("w_sh", 0.0)', 'c2["w_r"]',
                    'self.cfg.get("steps")', 'tcfg["views_per_rank"]', 'load_config([])["loss"]',
                    'loss["rec_noise_share"]'}


def test_the_package_reads_no_config_key_by_string():
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel in LOADER:
            continue
        offenders += [f"retinexgs/{rel}:{hit}" for hit in string_reads(path.read_text(), str(path))]
    assert not offenders, "config keys read by string (read them as attributes of the typed Config):\n" + \
        "\n".join(offenders)


def test_load_config_returns_the_typed_config_and_plain_data_round_trips():
    cfg = load_config()
    assert isinstance(cfg, Config) and cfg.loss.w_tv == plain(cfg)["loss"]["w_tv"]
    data = plain(cfg)
    assert isinstance(data, dict) and isinstance(data["model"]["enhancement"], dict)
    assert yaml.safe_load(yaml.safe_dump(data)) == data
    assert load_config(base=data) == cfg


def test_the_config_has_no_mapping_methods():
    """Attributes only (the dict shim of the plain-dict days is gone): a read by string fails at once, in the
    package, the tests and the scripts alike, instead of working in one place and not in another."""
    cfg = load_config()
    for read in (lambda: cfg["loss"], lambda: cfg.loss["w_tv"], lambda: cfg.get("loss"), lambda: cfg.keys()):
        with pytest.raises((TypeError, AttributeError)):
            read()
    with pytest.raises(TypeError):
        cfg.loss["w_tv"] = 0.0
    for name in ("__getitem__", "__setitem__", "__contains__", "get", "keys"):
        assert not hasattr(Section, name), name


def test_the_tests_and_scripts_read_no_config_key_by_string():
    root = PACKAGE.parent
    offenders = []
    for folder in ("tests", "scripts", "experiments"):
        for path in sorted((root / folder).rglob("*.py")):
            if path.name == "test_typed_config.py":  # this file: the reads above are meant to fail
                continue
            offenders += [f"{folder}/{path.relative_to(root / folder).as_posix()}:{hit}"
                          for hit in string_reads(path.read_text(), str(path))]
    assert not offenders, "config keys read by string (the config has attributes only):\n" + "\n".join(offenders)


def _leaves(d, prefix=()):
    for k, v in d.items():
        if isinstance(v, dict) and k != "params":
            yield from _leaves(v, prefix + (k,))
        else:
            yield prefix + (k,)


def test_the_schema_and_default_yaml_hold_the_same_keys():
    raw = yaml.safe_load((configs_dir() / "default.yaml").read_text())
    assert set(_leaves(raw)) == set(_leaves(plain(load_config())))


def test_the_default_model_follows_default_yaml_not_old_fallbacks():
    """The fallbacks that disagreed with configs/default.yaml (background black, tone illumination, shoulder 1.0)
    are gone: the model takes what the config says."""
    raw = yaml.safe_load((configs_dir() / "default.yaml").read_text())
    enh = raw["model"]["enhancement"]
    assert (raw["model"]["background"], enh["tone"], enh["shoulder"]) == ("mean", "exposure", 0.5)  # the premise
    cfg = load_config()
    g = GaussianModel.from_points(torch.rand(8, 3), torch.rand(8, 3), cfg.model.sh_degree, cfg.model.init_opacity)
    model = RetinexGSModel(g, cfg.model, decomposed=True)
    assert model.has_background and model.tone.name == "exposure" and model.shoulder == 0.5
    other = load_config(overrides=["model.enhancement.shoulder=0.8", "model.background=black"])
    model = RetinexGSModel(g, other.model, decomposed=True)
    assert model.shoulder == 0.8 and not model.has_background
    assert model.with_enhancement(load_config().model.enhancement).shoulder == 0.5


def test_the_proxy_tone_maps_with_the_configs_shoulder():
    from retinexgs.model.tone import tone_map
    from retinexgs.train.benchmarks import proxy

    torch.manual_seed(0)
    R, L = torch.rand(8, 8, 3), torch.rand(8, 8, 1) * 0.3 + 0.05
    for shoulder in (0.5, 0.9):
        cfg = load_config(overrides=[f"model.enhancement.shoulder={shoulder}"])
        got = proxy.enhanced(R, L, 0.4, 0.6, cfg)
        want = tone_map(R, L.expand_as(R), torch.tensor(0.4), torch.tensor(0.6), "exposure", shoulder=shoulder)[0]
        assert torch.allclose(got, want)
    assert not torch.allclose(proxy.enhanced(R, L, 0.4, 0.6, load_config()),
                              proxy.enhanced(R, L, 0.4, 0.6, load_config(overrides=["model.enhancement.shoulder=1.0"])))


def test_a_run_recorded_before_last_event_keeps_its_uncapped_schedule(tmp_path):
    """density.last_event's old inline fallback (1.0, no cap) lives in the format-0 migration now
    (FORMAT_0_VALUES), the one place for what a run folder made before a key existed did."""
    from retinexgs.model.schedule import build_schedule
    from retinexgs.run.folder import read_run_config

    data = plain(load_config())
    del data["density"]["last_event"]
    data["scene"] = str(tmp_path)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    cfg, _ = read_run_config(tmp_path)
    assert cfg.density.last_event == 1.0
    uncapped = load_config(overrides=["density.last_event=1.0"])
    assert build_schedule(cfg).densify_stop == build_schedule(uncapped).densify_stop


def test_run_config_and_checkpoint_hold_plain_data(tmp_path):
    from retinexgs.run.folder import write_run_config

    write_run_config(tmp_path, load_config(), tmp_path)
    text = (tmp_path / "config.yaml").read_text()
    assert "!!python" not in text and yaml.safe_load(text)["loss"]["w_tv"] == load_config().loss.w_tv
