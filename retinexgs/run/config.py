"""Loading a config: ``configs/default.yaml`` deep-merged with override files and ``key.sub=value`` overrides
(:mod:`retinexgs.config.files`), then checked against the typed schema (:mod:`retinexgs.config.schema`) and
the rules that need the layers above the schema (the registered strategies' names, LR3M's tile defaults, the
schedule) before any work starts. Unknown keys are errors, so a typo in an override never silently does
nothing."""
from __future__ import annotations

from typing import Any, Callable, Dict, Iterable, List, Optional, Tuple, Union

from pydantic import ValidationError

from retinexgs.config.files import RawConfig, configs_dir, merge, parse_override, plain, read_yaml, \
    resolve_config_path
from retinexgs.config.schema import Config, ConfigSchema, field_expectation
from retinexgs.errors import UserError
from retinexgs.model.schedule import check_schedule


def _strategy_names() -> List[str]:
    from retinexgs.strategy import STRATEGIES  # at call time: the registry, filled by the strategies' modules

    return list(STRATEGIES)


def _tone_names() -> List[str]:
    from retinexgs.model.tones import TONES  # at call time: a tone registered after import (a plug-in) counts

    return list(TONES)


# Config keys whose choices are a registry in a layer above the schema: key path -> a function returning the
# allowed names. The schema holds these keys as plain strings; :func:`validate` checks them here, in the schema's
# words (``density.kind must be one of default, mcmc, got 'x'``). A new registry-backed key is one row.
CHOICES: Dict[Tuple[str, ...], Callable[[], List[str]]] = {
    ("density", "kind"): _strategy_names,
    ("model", "enhancement", "tone"): _tone_names,
}


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
    the schema (:mod:`retinexgs.config.schema`), the registries' names (:data:`CHOICES`) and the schedule checks;
    returns the typed :data:`Config`."""
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


def _label(keys: Tuple[str, ...], sources: Dict[Tuple[str, ...], str], base_label: str) -> str:
    """Where the value at ``keys`` came from: the key itself or a parent replaced by a value; else (a section's
    cross-field check) a key inside it; else the base config."""
    return next((sources[keys[:i]] for i in range(len(keys), 0, -1) if keys[:i] in sources), None) or next(
        (src for path, src in reversed(list(sources.items())) if path[:len(keys)] == keys), base_label)


def _describe_error(err: Dict[str, Any], sources: Dict[Tuple[str, ...], str], base_label: str) -> str:
    keys, expect, section = field_expectation(tuple(err["loc"]))
    name = ".".join(keys) or "config"
    label = _label(keys, sources, base_label)
    kind = err["type"]
    if kind == "extra_forbidden":
        extra = ".".join(str(p) for p in err["loc"])
        return f"{label}: unknown config key {extra} (not in the config schema, retinexgs/config/schema.py)"
    if kind == "missing":
        return f"{label}: config key {name} is missing"
    if kind == "value_error":  # a cross-field check of a section: its message names the keys
        return f"{label}: {err['ctx']['error']}"
    if section is not None and len(keys) == len([p for p in err["loc"] if isinstance(p, str)]):
        expect = f"a mapping with the keys {', '.join(section.model_fields)}"
    return f"{label}: {name} must be {expect or err['msg'].lower()}, got {err['input']!r}"


def _bad_choices(data: RawConfig, sources: Dict[Tuple[str, ...], str], base_label: str) -> Dict[Tuple[str, ...], str]:
    """key path -> the error line, for each :data:`CHOICES` key whose value is not one of its registry's names."""
    bad: Dict[Tuple[str, ...], str] = {}
    for keys, names in CHOICES.items():
        node: Any = data
        for k in keys:
            node = node.get(k) if isinstance(node, dict) else None
        allowed = names()
        if node is not None and node not in allowed:  # missing: the schema says so
            bad[keys] = (f"{_label(keys, sources, base_label)}: {'.'.join(keys)} must be one of "
                         f"{', '.join(allowed)}, got {node!r}")
    return bad


def _lr3m_tiles(given: Dict[str, Any]) -> Optional[str]:
    """LR3M's tiles need a margin that is a multiple of the stride and room for a core of 4 strides (the
    parameters not given take the algorithm's defaults, which live in retinexgs.retinex, above the schema)."""
    if not {"tile_margin", "stride", "tile_pixels"} & set(given):
        return None
    from retinexgs.retinex.lr3m import LR3MParams  # lazy: --help and configs without tiles stay fast

    d = LR3MParams()
    m, st, px = (given.get(k, getattr(d, k)) for k in ("tile_margin", "stride", "tile_pixels"))
    if m % st:
        return f"tile_margin ({m}) must be a multiple of stride ({st})"
    need = 2 * m + 4 * st
    if px < need * need:
        return f"tile_pixels ({px}) must be at least (2*tile_margin + 4*stride)^2 = {need * need}"
    return None


def validate(cfg: Union[Config, RawConfig], sources: Optional[Dict[Tuple[str, ...], str]] = None,
             base_label: str = "config") -> Config:
    """Check ``cfg`` against the schema, the registries' names (:data:`CHOICES`), LR3M's tiles and the schedule
    rules; returns the typed :data:`Config` (numbers typed as the schema says; :func:`plain` turns it back into
    data). The error names the key path, the value given, what was expected and where the value came from
    (``--set model.sh_degree=abc: model.sh_degree must be an integer 0..3, got 'abc'``)."""
    data, sources = plain(cfg), sources or {}
    bad = _bad_choices(data, sources, base_label)
    lines = list(bad.values())
    try:
        model = ConfigSchema.model_validate(data)
    except ValidationError as exc:
        for err in exc.errors():
            if field_expectation(tuple(err["loc"]))[0] in bad:  # said once, with the registry's names
                continue
            line = _describe_error(err, sources, base_label)
            if line not in lines:  # a union reports once per member
                lines.append(line)
        model = None
    if lines:
        more = f" (and {len(lines) - 3} more)" if len(lines) > 3 else ""
        raise UserError("; ".join(lines[:3]) + more)
    assert model is not None
    from retinexgs.model.tones import config_problem  # the rules the registered tone sets (a reference, the table)

    tone = config_problem(model.model.enhancement)
    if tone:
        raise UserError(f"{_label(('model', 'enhancement'), sources, base_label)}: {tone}")
    if model.decomposer.method == "lr3m":
        tiles = _lr3m_tiles(model.decomposer.params)
        if tiles:
            raise UserError(f"{_label(('decomposer', 'params'), sources, base_label)}: decomposer.params: lr3m's "
                            f"{tiles}")
    check_schedule(model)
    return model
