"""Configs as data: ``configs/default.yaml`` deep-merged with override files and ``key.sub=value`` overrides.
Unknown keys are errors, so a typo in an override never silently does nothing."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Dict, Iterable, Optional

import yaml

from retinexgs.errors import UserError

Config = Dict[str, Any]


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


def read_yaml(path: Path) -> Config:
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


def merge(base: Config, override: Config, where: str, strict: bool = True) -> Config:
    """Deep-merge ``override`` into a copy of ``base``; with ``strict``, keys must exist in ``base``."""
    out = copy.deepcopy(base)
    for key, value in override.items():
        if strict and key not in out:
            raise UserError(f"unknown config key {where}{key!r} (known: {', '.join(sorted(out))})")
        if isinstance(out.get(key), dict) and isinstance(value, dict) and key != "params":
            out[key] = merge(out[key], value, f"{where}{key}.", strict)
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_override(text: str) -> Config:
    """``a.b=3`` -> {"a": {"b": 3}} (the value is parsed as YAML)."""
    if "=" not in text:
        raise UserError(f"override {text!r} must look like key.sub=value")
    key, value = text.split("=", 1)
    try:
        out: Config = yaml.safe_load(value) if value.strip() else None
    except yaml.YAMLError as exc:
        raise UserError(f"--set {text}: the value is not valid YAML ({' '.join(str(exc).split())}); quote "
                        "strings that contain YAML syntax") from None
    for part in reversed(key.strip().split(".")):
        out = {part: out}
    return out


def load_config(files: Iterable[str] = (), overrides: Iterable[str] = (), base: Optional[Config] = None) -> Config:
    """default.yaml (or ``base``), then each file, then each ``key=value`` override."""
    cfg = base if base is not None else read_yaml(configs_dir() / "default.yaml")
    for f in files:
        path = resolve_config_path(f)
        cfg = merge(cfg, read_yaml(path), f"{path}: ")
    for o in overrides:
        cfg = merge(cfg, parse_override(o), "--set ")
    validate(cfg)
    return cfg


def validate(cfg: Config) -> None:
    """Range checks of the values a user is likely to get wrong."""
    if cfg["method"] not in ("retinexgs", "3dgs", "pre", "post"):
        raise UserError(f"method must be retinexgs, 3dgs, pre or post, got {cfg['method']!r}")
    if not isinstance(cfg["steps"], int) or cfg["steps"] < 1:
        raise UserError(f"steps must be a positive integer, got {cfg['steps']!r}")
    if cfg["decomposer"]["method"] not in ("lr3m", "lime", "none"):
        raise UserError(f"decomposer.method must be lr3m, lime or none, got {cfg['decomposer']['method']!r}")
    if not 0 <= cfg["model"]["sh_degree"] <= 3:
        raise UserError("model.sh_degree must be in 0..3")
    choices = {"exp_on": ("illumination", "image"), "exp_form": ("l2", "l1"), "spa_form": ("zero_dce", "paper"),
               "sh_reduction": ("mean", "sum")}
    for k, v in cfg["loss"].items():
        if k in choices:
            if v not in choices[k]:
                raise UserError(f"loss.{k} must be one of {', '.join(choices[k])}, got {v!r}")
            continue
        if isinstance(v, bool):
            continue
        if not isinstance(v, (int, float)) or v < 0:
            raise UserError(f"loss.{k} must be a non-negative number, got {v!r}")
