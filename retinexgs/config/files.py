"""Configs as plain data: where ``configs/`` is, YAML files read with errors that name them, the deep merge of
override files and ``key.sub=value`` overrides. Validation (the schema and the checks that need the layers above
it: strategies, the schedule) is :func:`retinexgs.run.config.load_config`'s."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Dict, Union

import yaml
from pydantic import BaseModel

from retinexgs.config.schema import Config
from retinexgs.errors import UserError

# A config as plain data: what YAML files hold and what the merge, the migrations of old runs and the resume rules
# work on, before it is validated into a typed :data:`Config`.
RawConfig = Dict[str, Any]


def plain(cfg: Union[Config, RawConfig]) -> RawConfig:
    """``cfg`` as plain data (nested dicts, lists, numbers, strings): what YAML and checkpoints store. The schema's
    tuples (``train.resolution``'s pairs) are lists, as YAML reads them back."""
    return _lists(cfg.model_dump()) if isinstance(cfg, BaseModel) else copy.deepcopy(cfg)


def _lists(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _lists(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_lists(v) for v in x]
    return x


def configs_dir() -> Path:
    """The folder holding default.yaml: the repository's configs/ or the installed copy."""
    here = Path(__file__).resolve().parent.parent  # the retinexgs package folder
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


# Mappings whose keys the schema checks (per method), not the defaults file: they start empty and add up.
FREE_MAPPINGS = ("params", "denoise_params")


def merge(base: RawConfig, override: RawConfig, where: str, strict: bool = True) -> RawConfig:
    """Deep-merge ``override`` into a copy of ``base``; with ``strict``, keys must exist in ``base``."""
    out = copy.deepcopy(base)
    if "method" in override and override["method"] != out.get("method") and "params" not in override \
            and isinstance(out.get("params"), dict):
        out["params"] = {}  # another method: the earlier params were the old method's
    for key, value in override.items():
        if strict and key not in out:
            raise UserError(f"unknown config key {where}{key} (known: {', '.join(sorted(out))})")
        if key in FREE_MAPPINGS and isinstance(out.get(key), dict) and isinstance(value, dict) and value:
            # A method's free-form parameters (checked per method by the schema) add up key by key, so two
            # `--set decomposer.params.X` keep both; `params: {}` resets them.
            out[key] = {**out[key], **copy.deepcopy(value)}
        elif isinstance(out.get(key), dict) and isinstance(value, dict) and key not in FREE_MAPPINGS:
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
