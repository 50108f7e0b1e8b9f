"""Versioned runs: the format number written in ``RUN/config.yaml`` and in every checkpoint, and one migration a
format step that turns what an older version wrote into what this one reads.

The rule: a change that makes an existing run behave differently when read back (a new key whose default is not
what runs made before it did, a renamed or regrouped key, a checkpoint field that changed meaning) raises
:data:`FORMAT` by one and adds the migration from the previous format to :data:`CONFIG_MIGRATIONS` (and
:data:`CHECKPOINT_MIGRATIONS` when checkpoints change). A new key whose default is what older runs did needs no
step: whatever a recorded config lacks after its migrations is taken from ``configs/default.yaml``. A key deleted
(an option that lost its ablation, or that no experiment ever measured) is dropped by the next step where the run
used its old default, and the run is refused in one line where it did not (this code cannot reproduce it). A format
newer than this code knows is refused in one line (reading it as ours would silently be wrong). Format 0 is every run
written before formats existed (no ``format`` key)."""
from __future__ import annotations

import copy
from typing import Any, Callable, Dict, List, Tuple

from retinexgs.config.files import RawConfig, configs_dir, read_yaml
from retinexgs.errors import UserError

FORMAT = 8  # the format this code writes

# Format 0 -> 1: the keys whose default changed after they were added. A run made before a key existed behaved as
# the value here, not as today's default (which would re-render it differently). The tone form was the gamma on L̂
# until 2026-11-25, when the exposure tone became the default; the depth prior came in later that day, at weight
# 0.3 in the default (a run made before it, resumed, must not start using it); the reconstruction term was on the
# dark photo's values (rec_domain photo) until the exposed SSIM became the default, later still; renders were over
# black until the mean background became the default (2026-11-26), and blind to the capture's noise until issue 32
# (the noise floor of the exposed SSIM, the camera's clipped noise). The exposure meter averaged until the
# highlight cap (2026-11-27), and a batch of views stepped with torch's Adam betas until β^B (the same day).
# Density events ran to density.stop until density.last_event capped them. A raw scene's priors weighed every
# pixel alike until loss.rec_raw_prior_snr (2026-11-28), and renders drew Gaussians up to 0.01 from the camera
# until model.near_fraction (the same day). A raw scene's tone took the photos' highlight knee until
# model.enhancement.shoulder_raw (the same day), and its L_spa read the unclipped target until loss.spa_raw. A
# folder posed by SfM was used whatever share of its photos SfM registered until data.min_registered, and the 2D
# priors read the noisy views until decomposer.denoise.
# The keys are named as format 1 named them (the raw ones move in config_1_to_2). density.noise_aware and
# loss.rec_camera_noise are gone (format 3 deleted them): each one's format-0 value was its default, which is how
# every run without it trains.
FORMAT_0_VALUES: Dict[str, Any] = {
    "model.enhancement.tone": "illumination", "loss.w_depth": 0.0, "loss.rec_domain": "photo",
    "model.background": "black", "model.enhancement.shoulder": 1.0, "loss.rec_noise_floor": False,
    "loss.rec_noise_share": 0.5,
    "loss.rec_noise_scale": 1, "loss.exp_highlight_share": 0.0, "train.momentum_batch_scaling": "none",
    "density.last_event": 1.0, "loss.rec_raw": "photo", "decomposer.raw_denoise": False,
    "loss.rec_raw_unit": "plain", "loss.rec_raw_prior_snr": 0.0, "model.near_fraction": 0.0,
    "model.enhancement.shoulder_raw": None, "loss.spa_raw": "extended", "data.min_registered": 0.0,
    "decomposer.denoise": "none"}


def _set_missing(cfg: RawConfig, values: Dict[str, Any], filled: List[str]) -> None:
    """Set each dotted key of ``values`` that ``cfg`` lacks (making its sections as needed: a run that lacks a
    whole section predates every key in it)."""
    for dotted, value in values.items():
        *sections, key = dotted.split(".")
        node = cfg
        for name in sections:
            if not isinstance(node.get(name, {}), dict):
                break  # not a section: the schema names that error
            node = node.setdefault(name, {})
        else:
            if key not in node:
                node[key] = copy.deepcopy(value)
                filled.append(dotted)


def _section_of(cfg: RawConfig, dotted: str) -> Tuple[Any, str]:
    """(the section holding a dotted key, or None where a section on the way is missing or not a mapping; the
    key's own name): the read-only walk of the migrations that move or drop keys."""
    *sections, key = dotted.split(".")
    node: Any = cfg
    for name in sections:
        node = node.get(name) if isinstance(node, dict) else None
    return node, key


def config_0_to_1(cfg: RawConfig, filled: List[str]) -> RawConfig:
    """Format 0 -> 1: the values runs had before the keys of :data:`FORMAT_0_VALUES` existed."""
    _set_missing(cfg, FORMAT_0_VALUES, filled)
    return cfg


# Format 1 -> 2 (issue 63): the camera-raw scenes' own keys grouped under ``raw`` sections instead of ``*_raw``
# suffixes (retinexgs.data.capture reads them): old dotted key -> new dotted key, values unchanged.
RAW_KEYS_1_TO_2: Dict[str, str] = {
    "decomposer.raw_denoise": "decomposer.raw.preview_denoise",
    "model.enhancement.shoulder_raw": "model.enhancement.raw.shoulder",
    "loss.rec_raw": "loss.raw.mode", "loss.rec_raw_model_error": "loss.raw.model_error",
    "loss.rec_raw_unit": "loss.raw.unit", "loss.rec_raw_prior_snr": "loss.raw.prior_snr",
    "loss.spa_raw": "loss.raw.spa"}


def config_1_to_2(cfg: RawConfig, filled: List[str]) -> RawConfig:
    """Format 1 -> 2: each key of :data:`RAW_KEYS_1_TO_2` the config has moves to its new place (a value already
    there is kept: the new key was written on purpose). A format-0 run gets the format-0 values first
    (:data:`FORMAT_0_VALUES`, by their format-1 names), then this move."""
    for old, new in RAW_KEYS_1_TO_2.items():
        node, old_key = _section_of(cfg, old)
        if not isinstance(node, dict) or old_key not in node:
            continue
        value = node.pop(old_key)
        *new_sections, new_key = new.split(".")
        target = cfg
        for name in new_sections:
            if not isinstance(target.get(name, {}), dict):
                break  # not a section: the schema names that error
            target = target.setdefault(name, {})
        else:
            target.setdefault(new_key, value)
    filled[:] = [RAW_KEYS_1_TO_2.get(key, key) for key in filled]  # a format-0 run's filled keys, by today's names
    return cfg


# Format 2 -> 3 (issue 63): the options that only an ablation switched on and whose ablation lost, or that no
# experiment ever measured (model.enhancement.per_channel), deleted with the code that implemented them: dotted
# key -> the default every run had unless it set the option on purpose.
REMOVED_2_TO_3: Dict[str, Any] = {
    "model.illumination.leak": 0.0, "model.enhancement.debias_black": False, "model.enhancement.black_filter": 0,
    "loss.raw.model_error": 0.0, "density.noise_aware": False, "loss.rec_huber": 0.0,
    "loss.rec_ssim_noise": False, "loss.rec_camera_noise": False, "model.enhancement.per_channel": False}


def _drop_removed(cfg: RawConfig, removed: Dict[str, Any]) -> None:
    """Take each dotted key of ``removed`` out of ``cfg``; UserError (one line, naming the key and its value)
    where the recorded value is not the old default: the run used an option this code no longer has."""
    for dotted, default in removed.items():
        node, key = _section_of(cfg, dotted)
        if not isinstance(node, dict) or key not in node:
            continue
        value = node.pop(key)
        if isinstance(value, bool) != isinstance(default, bool) or value != default:
            raise UserError(f"{dotted} is {value!r}: that option was removed from retinexgs (it lost its ablation or "
                            "was never measured), so this version cannot reproduce the run; use the retinexgs that "
                            "made it")


# Format 2 -> 3, keys added with a default that is not what older runs did (issue 64): a bare folder's SfM previews were
# not denoised before data.sfm_denoise, and SfM runs again on --resume when the cached model's recipe differs. The 2D
# priors' denoiser ran OpenCV's NLM before decomposer.denoise_backend, whose auto picks torch's on CUDA: its output
# differs by a few levels and keys the priors' cache apart, so a resumed run would train on recomputed priors.
ADDED_2_TO_3: Dict[str, Any] = {"data.sfm_denoise": "none", "decomposer.denoise_backend": "opencv"}


def config_2_to_3(cfg: RawConfig, filled: List[str]) -> RawConfig:
    """Format 2 -> 3: the keys of :data:`REMOVED_2_TO_3` dropped where they hold their old default (the run
    behaves as it did); a run that set one of them otherwise is refused in one line. The keys of
    :data:`ADDED_2_TO_3` the config lacks get the value older runs had."""
    _drop_removed(cfg, REMOVED_2_TO_3)
    _set_missing(cfg, ADDED_2_TO_3, filled)
    return cfg


# Format 3 -> 4: the priors' luma NLM kept h_luma whatever the views per point before decomposer.denoise_luma_views.
ADDED_3_TO_4: Dict[str, Any] = {"decomposer.denoise_luma_views": 0}


def config_3_to_4(cfg: RawConfig, filled: List[str]) -> RawConfig:
    """Format 3 -> 4: the keys of :data:`ADDED_3_TO_4` the config lacks get the value older runs had."""
    _set_missing(cfg, ADDED_3_TO_4, filled)
    return cfg


# Format 4 -> 5 (issue 64): a raw scene's reflectance prior supervised R̂'s luma too before loss.raw.r_prior_luma.
ADDED_4_TO_5: Dict[str, Any] = {"loss.raw.r_prior_luma": 1.0}


def config_4_to_5(cfg: RawConfig, filled: List[str]) -> RawConfig:
    """Format 4 -> 5: the keys of :data:`ADDED_4_TO_5` the config lacks get the value older runs had."""
    _set_missing(cfg, ADDED_4_TO_5, filled)
    return cfg


def config_5_to_6(cfg: RawConfig, filled: List[str]) -> RawConfig:
    """Format 5 -> 6 (issue 64): a raw scene's views binned by data.downscale read the R prior with the one κ of
    loss.raw.r_prior_luma before loss.raw.r_prior_luma_binned: the new key takes that value where it is missing."""
    node, _ = _section_of(cfg, "loss.raw.r_prior_luma")
    kappa = node.get("r_prior_luma", 0.0) if isinstance(node, dict) else 0.0
    _set_missing(cfg, {"loss.raw.r_prior_luma_binned": kappa}, filled)
    return cfg


# Format 6 -> 7 (issue 65): runs trained at full size throughout (train.resolution []) until the coarse-to-fine
# schedule became the default, and a schedule pooled every view by its stage's k before train.resolution_min_pixels.
ADDED_6_TO_7: Dict[str, Any] = {"train.resolution": [], "train.resolution_min_pixels": 0}


def config_6_to_7(cfg: RawConfig, filled: List[str]) -> RawConfig:
    """Format 6 -> 7: the keys of :data:`ADDED_6_TO_7` the config lacks get the value older runs had."""
    _set_missing(cfg, ADDED_6_TO_7, filled)
    return cfg


# Format 7 -> 8 (issue 64): the priors kept their weights to the end of a run before loss.prior_late_views.
ADDED_7_TO_8: Dict[str, Any] = {"loss.prior_late_views": 0}


def config_7_to_8(cfg: RawConfig, filled: List[str]) -> RawConfig:
    """Format 7 -> 8: the keys of :data:`ADDED_7_TO_8` the config lacks get the value older runs had."""
    _set_missing(cfg, ADDED_7_TO_8, filled)
    return cfg


def checkpoint_0_to_1(state: Dict[str, Any]) -> Dict[str, Any]:
    """Format 0 -> 1: checkpoint fields older versions did not write: no training time recorded (0 s), no view
    order (a fresh shuffle), no strategy statistics, no record of the training views."""
    for key, value in (("train_seconds", 0.0), ("order", []), ("density", {}), ("train_views", None)):
        state.setdefault(key, value)
    return state


def checkpoint_2_to_3(state: Dict[str, Any]) -> Dict[str, Any]:
    """Format 2 -> 3: the fields only ``density.noise_aware`` used (its probe's random state, the default
    strategy's squared-gradient sums) are dropped; nothing reads them now."""
    state.pop("noise_probe_rng", None)
    if isinstance(state.get("density"), dict):
        for key in ("grad_sq", "noise_sq", "noise_count"):
            state["density"].pop(key, None)
    return state


def _checkpoint_same(state: Dict[str, Any]) -> Dict[str, Any]:
    """A step whose checkpoint fields did not change (its config is migrated by :func:`migrate_checkpoint`)."""
    return state


# CONFIG_MIGRATIONS[n] turns format n into n + 1 (likewise for checkpoints' own fields): FORMAT steps each
# (tests/test_run_format.py checks it).
CONFIG_MIGRATIONS: List[Callable[[RawConfig, List[str]], RawConfig]] = [config_0_to_1, config_1_to_2, config_2_to_3,
                                                                     config_3_to_4, config_4_to_5, config_5_to_6,
                                                                     config_6_to_7, config_7_to_8]
CHECKPOINT_MIGRATIONS: List[Callable[[Dict[str, Any]], Dict[str, Any]]] = [checkpoint_0_to_1, _checkpoint_same,
                                                                          checkpoint_2_to_3, _checkpoint_same,
                                                                          _checkpoint_same, _checkpoint_same,
                                                                          _checkpoint_same, _checkpoint_same]


def format_of(data: Dict[str, Any], where: str) -> int:
    """The format ``data`` (a recorded config or a checkpoint) was written in: 0 without a ``format`` key; a
    format newer than :data:`FORMAT`, or not a whole number, is refused in one line naming ``where``."""
    fmt = data.get("format", 0)
    if isinstance(fmt, bool) or not isinstance(fmt, int) or fmt < 0:
        raise UserError(f"{where}: format must be a whole number 0..{FORMAT}, got {fmt!r}")
    if fmt > FORMAT:
        raise UserError(f"{where} is in run format {fmt}, newer than this retinexgs reads (format {FORMAT}): "
                        "update retinexgs to read it")
    return fmt


def _fill_defaults(cfg: RawConfig, default: RawConfig, prefix: str, filled: List[str]) -> RawConfig:
    for key, value in default.items():
        if key not in cfg:
            cfg[key] = copy.deepcopy(value)
            filled.append(prefix + key)
        elif isinstance(value, dict) and isinstance(cfg[key], dict) and key != "params":
            _fill_defaults(cfg[key], value, f"{prefix}{key}.", filled)
    return cfg


def migrate_config(recorded: RawConfig, where: str) -> Tuple[RawConfig, List[str]]:
    """A recorded config (plain data, with or without its ``format`` key) as this version reads it: each
    migration from its format on, then the keys still missing from ``configs/default.yaml``. Returns the config
    (without ``format``; not validated yet) and the dotted keys it lacked."""
    fmt = format_of(recorded, where)
    cfg = copy.deepcopy(recorded)
    cfg.pop("format", None)
    filled: List[str] = []
    for step in CONFIG_MIGRATIONS[fmt:]:
        try:
            cfg = step(cfg, filled)
        except UserError as exc:  # a step names the key; the reader needs the file too
            raise UserError(f"{where}: {exc}") from None
    _fill_defaults(cfg, read_yaml(configs_dir() / "default.yaml"), "", filled)
    return cfg, filled


def migrate_checkpoint(state: Dict[str, Any], where: str) -> Dict[str, Any]:
    """A loaded checkpoint as this version reads it: its own fields and its config migrated from its format to
    :data:`FORMAT` (which it then carries)."""
    fmt = format_of(state, where)
    for step in CHECKPOINT_MIGRATIONS[fmt:]:
        state = step(state)
    if isinstance(state.get("config"), dict):
        state["config"] = migrate_config({**state["config"], "format": fmt}, where)[0]
    state["format"] = FORMAT
    return state
