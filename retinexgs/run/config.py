"""Configs as data: ``configs/default.yaml`` deep-merged with override files and ``key.sub=value`` overrides,
then checked against one typed schema (:mod:`retinexgs.run.schema`) before any work starts. Unknown keys are
errors, so a typo in an override never silently does nothing."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Dict, Iterable, Optional, Tuple, Union

import yaml
from pydantic import BaseModel, ValidationError

from retinexgs.errors import UserError
from retinexgs.model.schedule import check_schedule
from retinexgs.run.schema import Config, ConfigSchema, field_expectation  # noqa: F401 (Config re-exported)

# A config as plain data: what YAML files hold and what the merge, the predating fill and the resume rules
# work on, before it is validated into a typed :data:`Config`.
RawConfig = Dict[str, Any]


def plain(cfg: Union[Config, RawConfig]) -> RawConfig:
    """``cfg`` as plain data (nested dicts, lists, numbers, strings): what YAML and checkpoints store."""
    return cfg.model_dump() if isinstance(cfg, BaseModel) else copy.deepcopy(cfg)


def configs_dir() -> Path:
    """The folder holding default.yaml: the repository's configs/ or the installed copy."""
    here = Path(__file__).resolve().parent.parent
    for candidate in (here.parent / "configs", here / "configs"):
        if (candidate / "default.yaml").is_file():
            return candidate
    raise UserError("configs/default.yaml not found: the installation is incomplete; reinstall retinexgs")


def resolve_config_path(name: str) -> Path:
    """A config file by path, or by name inside configs/ (``demo``, ``ablations/no_tv``)."""
    p = Path(name)
    if p.is_file():
        return p
    for candidate in (configs_dir() / name, configs_dir() / f"{name}.yaml"):
        if candidate.is_file():
            return candidate
    raise UserError(f"config {name!r} not found (neither a file nor a name in {configs_dir()})")


def read_yaml(path: Path) -> RawConfig:
    """Read one YAML mapping with an error that names the file."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise UserError(f"cannot read config {path}: {exc.strerror or exc}") from exc
    except yaml.YAMLError as exc:
        raise UserError(f"config {path} is not valid YAML: {exc}") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise UserError(f"config {path} must be a mapping of keys to values, got {type(data).__name__}")
    return data


def merge(base: RawConfig, override: RawConfig, where: str, strict: bool = True) -> RawConfig:
    """Deep-merge ``override`` into a copy of ``base``; with ``strict``, keys must exist in ``base``."""
    out = copy.deepcopy(base)
    if "method" in override and override["method"] != out.get("method") and "params" not in override \
            and isinstance(out.get("params"), dict):
        out["params"] = {}  # another method: the earlier params were the old method's
    for key, value in override.items():
        if strict and key not in out:
            raise UserError(f"unknown config key {where}{key} (known: {', '.join(sorted(out))})")
        if key == "params" and isinstance(out.get(key), dict) and isinstance(value, dict) and value:
            # A method's free-form parameters (checked per method by the schema) add up key by key, so two
            # `--set decomposer.params.X` keep both; `params: {}` resets them.
            out[key] = {**out[key], **copy.deepcopy(value)}
        elif isinstance(out.get(key), dict) and isinstance(value, dict) and key != "params":
            out[key] = merge(out[key], value, f"{where}{key}.", strict)
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_override(text: str) -> RawConfig:
    """``a.b=3`` -> {"a": {"b": 3}} (the value is parsed as YAML)."""
    if "=" not in text:
        raise UserError(f"override {text!r} must look like key.sub=value")
    key, value = text.split("=", 1)
    try:
        out: RawConfig = yaml.safe_load(value) if value.strip() else None
    except yaml.YAMLError as exc:
        raise UserError(f"--set {text}: the value is not valid YAML ({' '.join(str(exc).split())}); quote "
                        "strings that contain YAML syntax") from None
    for part in reversed(key.strip().split(".")):
        out = {part: out}
    return out


def _note_sources(data: RawConfig, prefix: Tuple[str, ...], label: str, sources: Dict[Tuple[str, ...], str]) -> None:
    """Remember which file or ``--set`` gave each key (for error messages)."""
    for key, value in data.items():
        path = prefix + (str(key),)
        if isinstance(value, dict) and key != "params":
            _note_sources(value, path, label, sources)
        else:
            sources[path] = label


def load_config(files: Iterable[str] = (), overrides: Iterable[str] = (),
                base: Optional[Union[Config, RawConfig]] = None, base_label: Optional[str] = None) -> Config:
    """default.yaml (or ``base``, typed or plain), then each file, then each ``key=value`` override, validated by
    the schema (:mod:`retinexgs.run.schema`) and the schedule checks; returns the typed :data:`Config`."""
    if base is None:
        cfg, base_label = read_yaml(configs_dir() / "default.yaml"), str(configs_dir() / "default.yaml")
    else:
        cfg = plain(base)
    sources: Dict[Tuple[str, ...], str] = {}
    for f in files:
        path = resolve_config_path(f)
        data = read_yaml(path)
        cfg = merge(cfg, data, f"{path}: ")
        _note_sources(data, (), f"config {path}", sources)
    for o in overrides:
        data = parse_override(o)
        cfg = merge(cfg, data, "--set ")
        _note_sources(data, (), f"--set {o}", sources)
    return validate(cfg, sources, base_label or "config")


def _describe_error(err: Dict[str, Any], sources: Dict[Tuple[str, ...], str], base_label: str) -> str:
    keys, expect, section = field_expectation(tuple(err["loc"]))
    name = ".".join(keys) or "config"
    # The key itself or a parent replaced by a value; else (a section's cross-field check) a key inside it.
    label = next((sources[keys[:i]] for i in range(len(keys), 0, -1) if keys[:i] in sources), None) or next(
        (src for path, src in reversed(list(sources.items())) if path[:len(keys)] == keys), base_label)
    kind = err["type"]
    if kind == "extra_forbidden":
        extra = ".".join(str(p) for p in err["loc"])
        return f"{label}: unknown config key {extra} (not in the config schema, retinexgs/run/schema.py)"
    if kind == "missing":
        return f"{label}: config key {name} is missing"
    if kind == "value_error":  # a cross-field check of a section: its message names the keys
        return f"{label}: {err['ctx']['error']}"
    if section is not None and len(keys) == len([p for p in err["loc"] if isinstance(p, str)]):
        expect = f"a mapping with the keys {', '.join(section.model_fields)}"
    return f"{label}: {name} must be {expect or err['msg'].lower()}, got {err['input']!r}"


def validate(cfg: Union[Config, RawConfig], sources: Optional[Dict[Tuple[str, ...], str]] = None,
             base_label: str = "config") -> Config:
    """Check ``cfg`` against the schema and the schedule rules; returns the typed :data:`Config` (numbers typed
    as the schema says; :func:`plain` turns it back into data). The error names the key path, the value given, what was expected and where the
    value came from (``--set model.sh_degree=abc: model.sh_degree must be an integer 0..3, got 'abc'``)."""
    try:
        model = ConfigSchema.model_validate(plain(cfg))
    except ValidationError as exc:
        seen, lines = set(), []
        for err in exc.errors():
            line = _describe_error(err, sources or {}, base_label)
            if line not in seen:  # a union reports once per member
                seen.add(line)
                lines.append(line)
        more = f" (and {len(lines) - 3} more)" if len(lines) > 3 else ""
        raise UserError("; ".join(lines[:3]) + more) from None
    check_schedule(model)
    return model
