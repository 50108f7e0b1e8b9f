"""The typed schema of a config (pydantic v2): one class per section of ``configs/default.yaml``.

It sits at the bottom of the layers (it imports nothing of the package), so model/, strategy/, data/ and train/
import their section types at runtime. A choice whose names live in a layer above (``density.kind``: the
registered strategies) is a plain string here, checked against its registry by the loader
(:data:`retinexgs.run.config.CHOICES`), which sits above those registries.

Every field says what it expects with :class:`Expect` (used verbatim in error messages), so a bad value reads
``model.sh_degree must be an integer 0..3, got 'abc'``. Unknown keys are refused (``extra="forbid"``) and
types are strict (no silent ``"3"`` -> 3 or ``true`` -> 1); the only coercion is a YAML string that spells a
number (PyYAML reads ``1e-4`` as a string) into a float.

To add a config key: add it to ``configs/default.yaml`` and a field to its section's class here, built with
the helpers below (``Int``, ``Num``, ``Bool``, ``Choice``, ``Step``, ``Every``, ...);
``tests/test_config_schema.py`` checks that every shipped config validates. When its default changes what a
run made before it does, raise the run format and add that step's migration (:mod:`retinexgs.config.versions`).
"""
from __future__ import annotations

import re
from typing import Annotated, Any, Dict, List, Literal, Optional, Tuple, Union

from pydantic import (AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, StrictInt, ValidationError,
                      ValidationInfo, field_validator, model_validator)


class Expect:
    """Annotation metadata: what a field expects, in words (pydantic ignores it; the error formatter reads it)."""

    def __init__(self, text: str) -> None:
        self.text = text


_NUMBER = re.compile(r"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*$")


def _yaml_number(value: Any) -> Any:
    """PyYAML reads ``1e-4`` (no dot) as a string: accept a string that spells a number as that number."""
    if isinstance(value, str) and _NUMBER.match(value):
        return float(value)
    return value


def _zero_or_at_least_one(value: float) -> float:
    """``train.pair_margin``: a buffer below the counts it is sized from would overflow every step."""
    if 0 < value < 1:
        raise ValueError("must be 0 or >= 1")
    return value


def _range(lo: Optional[float], hi: Optional[float], lo_open: bool = False) -> str:
    if lo is not None and hi is not None:
        return f"{lo}..{hi}" if not lo_open else f"in ({lo}, {hi}]"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo}"
    return f"<= {hi}" if hi is not None else ""


def Int(lo: Optional[int] = None, hi: Optional[int] = None) -> Any:
    """An integer (not a bool, not 2.0) within [lo, hi]."""
    text = f"an integer {_range(lo, hi)}".strip()
    return Annotated[int, Field(ge=lo, le=hi), Expect(text)]


def Num(ge: Optional[float] = None, gt: Optional[float] = None, le: Optional[float] = None) -> Any:
    """A finite number (int or float, not a bool) within the bounds (``1e400`` reads as inf: refused too)."""
    lo, lo_open = (gt, True) if gt is not None else (ge, False)
    text = f"a number {_range(lo, le, lo_open)}".strip()
    return Annotated[float, BeforeValidator(_yaml_number), Field(ge=ge, gt=gt, le=le, allow_inf_nan=False),
                     Expect(text)]


Bool = Annotated[bool, Expect("true or false")]
OptStr = Annotated[Optional[str], Expect("a string or null")]


def Choice(*values: str) -> Any:
    """One of ``values`` (a Literal)."""
    return Annotated[Literal[values], Expect("one of " + ", ".join(values))]  # type: ignore[valid-type]


# Schedule points (retinexgs.model.schedule): a decimal 0..1 is a fraction of `steps`, so the schedule follows the
# run length; an integer is an absolute step number (sklearn's test_size convention).
Step = Annotated[Union[Annotated[StrictInt, Field(ge=0)], Annotated[float, Field(ge=0, le=1)]],
                 Expect("a fraction of steps 0..1 (a decimal, e.g. 0.3) or an absolute step (an integer >= 0)")]
Every = Annotated[Union[Annotated[StrictInt, Field(ge=1)], Annotated[float, Field(gt=0, le=1)]],
                  Expect("an interval: a fraction of steps in (0, 1] (a decimal, e.g. 0.01) or a number of steps "
                         "(an integer >= 1)")]
EveryOrOff = Annotated[Union[Annotated[StrictInt, Field(ge=0)], Annotated[float, Field(ge=0, le=1)]],
                       Expect("an interval: a fraction of steps 0..1 (a decimal, e.g. 0.3), a number of steps "
                              "(an integer >= 1), or 0 for never")]


def _pairs(value: Any) -> Any:
    """A YAML list of two-item lists as a list of tuples (strict mode reads a tuple field from tuples only)."""
    if isinstance(value, list):
        return [tuple(v) if isinstance(v, list) else v for v in value]
    return value


class Section(BaseModel):
    """A config section: strict types, unknown keys refused. Read by attribute only (``cfg.loss.w_tv``), so
    that an editor finds every user of a key; a config as data is :func:`retinexgs.config.plain`'s
    ``model_dump()``. Assignment is not validated (``validate_assignment`` off): code that edits a config sets
    values the schema already accepted."""

    model_config = ConfigDict(extra="forbid", strict=True)


class Data(Section):
    reader: Choice("auto", "transforms", "colmap", "sfm")
    downscale: Num(ge=1)
    cache_dir: OptStr
    white_balance: Choice("as-shot", "grey-edge")
    min_registered: Num(ge=0, le=1)
    sfm_denoise: Choice("auto", "none", "nlm", "chroma")


# ---- the decomposers' parameters (decomposer.params), one class per method: every field of the method's params
# dataclass (retinexgs.retinex.lr3m.LR3MParams, retinexgs.retinex.lime.LIMEParams; tests/test_newcomer_caches.py
# checks that the names match). Each field defaults to None = "not given": only the keys a config sets are checked
# and passed on, the dataclass supplies the rest.

class LR3MParamsSchema(Section):
    beta: Num(ge=0) = None
    omega: Num(ge=0) = None
    lam: Num(ge=0) = None
    sigma: Num(gt=0) = None
    eps: Num(ge=0) = None
    gamma: Num(gt=0) = None
    delta: Num() = None  # published, unused
    gamma_s: Num(gt=0, le=1) = None
    mu0: Num(gt=0) = None
    rho: Num(ge=1) = None
    iterations: Int(1) = None
    patch: Int(2) = None
    stride: Int(1) = None
    search_radius: Int(0) = None
    search_step: Int(1) = None
    group_size: Int(1) = None
    c1: Num(ge=0) = None
    illum_eps: Num(gt=0) = None
    weight_sigma: Num(ge=0) = None
    cg_tol: Num(gt=0) = None
    cg_max_iter: Int(1) = None
    grad_noise_k: Num(ge=0) = None
    l_floor: Num(gt=0, le=1) = None
    median_guide: Bool = None
    rematch_every: Int(0) = None
    solver: Choice("gram", "svd") = None
    tile_pixels: Int(1) = None
    tile_margin: Int(0) = None
    tile_memory_share: Num(ge=0) = None


class LIMEParamsSchema(Section):
    alpha: Num(ge=0) = None
    eps: Num(gt=0) = None
    weight_sigma: Num(ge=0) = None
    gamma: Num(gt=0) = None
    l_floor: Num(gt=0, le=1) = None
    cg_tol: Num(gt=0) = None
    cg_max_iter: Int(1) = None


class DenoiseParamsSchema(Section):
    """``decomposer.denoise_params``: the denoiser's settings (retinexgs.retinex.denoise.DenoiseParams)."""

    h_luma: Num(ge=0) = None
    h_chroma: Num(ge=0) = None
    patch: Int(1) = None
    search: Int(1) = None
    radius: Int(1) = None
    eps: Num(gt=0) = None
    calibrate: Bool = None


# method -> its parameters' schema; "none" (no decomposition) reads no parameters and checks none; "denoise" names
# the denoiser's settings (decomposer.denoise_params), checked the same way.
DECOMPOSER_PARAMS: Dict[str, type] = {"lr3m": LR3MParamsSchema, "lime": LIMEParamsSchema,
                                      "denoise": DenoiseParamsSchema}


def check_decomposer_params(method: str, params: Dict[str, Any], where: str = "decomposer.params") -> Dict[str, Any]:
    """``params`` (a mapping of some of ``method``'s parameters) checked against the method's schema: known
    names, types and ranges. Returns them with their values as typed (a number spelled as a string, or an
    integer for a float parameter, becomes a float); raises ValueError naming ``where.<key>``, what it expects
    and the value given. A method without a schema (``none``) reads no parameters: returned as they are. Rules
    between a method's parameters and its defaults (LR3M's tiles) are the loader's
    (:func:`retinexgs.run.config.validate`): the defaults live with the algorithm, in a layer above."""
    schema = DECOMPOSER_PARAMS.get(method)
    if schema is None:
        return dict(params)
    try:
        model = schema.model_validate(dict(params))
    except ValidationError as exc:
        names = ", ".join(schema.model_fields)
        lines = []
        for err in exc.errors():
            key = str(err["loc"][0]) if err["loc"] else "?"
            if err["type"] == "extra_forbidden":
                lines.append(f"unknown config key {where}.{key}: {method} has no parameter {key!r} "
                             f"(its parameters: {names})")
                continue
            info = schema.model_fields.get(key)
            expect = next((m.text for m in info.metadata if isinstance(m, Expect)), None) if info else None
            line = f"{where}.{key} must be {expect or err['msg'].lower()}, got {err['input']!r}"
            if line not in lines:  # a union reports once per member
                lines.append(line)
        raise ValueError("; ".join(lines)) from None
    return {k: getattr(model, k) for k in params}


class DecomposerRaw(Section):
    """``decomposer.raw``: read on camera-raw scenes only (retinexgs.data.capture)."""

    preview_denoise: Bool  # the priors from a denoised linear preview of the raw view


class Decomposer(Section):
    method: Choice("lr3m", "lime", "none")
    # The method's parameters, checked by its schema above (names, types, ranges) before anything loads.
    params: Annotated[Dict[str, Any], Expect("a mapping of the decomposer's parameters")]
    device: OptStr
    raw: DecomposerRaw
    denoise: Choice("auto", "none", "nlm", "chroma")  # the 2D priors' photo through a denoiser (retinex/denoise.py)
    denoise_backend: Choice("auto", "torch", "opencv")  # who runs its non-local means (auto: torch on CUDA)
    # steps (or fractions of the run) after which the priors are made again from the views re-denoised with the
    # model's render as the pilot (retinexgs/train/redenoise.py)
    redenoise_at: Annotated[List[Step], Expect("a list of steps (integers) or fractions of the run (decimals 0..1), "
                                               "e.g. [0.3, 0.6]; [] for never")]
    redenoise_chroma: Choice("pilot", "denoiser")  # whose chroma the re-denoised view keeps (the render's gains or the single-view denoiser's)
    redenoise_source: Choice("render", "views")  # what re-denoises a view: the render's Wiener gains, or its neighbours warped in by the model's depth
    # overrides of the denoiser's settings, checked by DenoiseParamsSchema
    denoise_params: Annotated[Dict[str, Any], Expect("a mapping of the denoiser's settings")]
    # the median views per point up to which the luma NLM keeps its h_luma; above, h_luma·√(this/n) (0: off)
    denoise_luma_views: Num(ge=0)

    @field_validator("denoise_params", mode="after")
    @classmethod
    def _known_denoise_params(cls, params: Dict[str, Any]) -> Dict[str, Any]:
        return check_decomposer_params("denoise", params, "decomposer.denoise_params")

    @field_validator("params", mode="after")
    @classmethod
    def _known_params(cls, params: Dict[str, Any], info: ValidationInfo) -> Dict[str, Any]:
        method = info.data.get("method")
        if method is None:  # the method itself is wrong: that error is the one to read
            return params
        return check_decomposer_params(method, params)


class Illumination(Section):
    pos_freqs: Int(0)
    dir_freqs: Int(0)
    hidden: Int(1)
    depth: Int(1)
    dir_hidden: Int(1)
    init_value: Num(gt=0)
    view_dependent: Bool


class EnhancementRaw(Section):
    """``model.enhancement.raw``: read on camera-raw scenes only (retinexgs.data.capture)."""

    # the knee on a camera-raw scene (null: ``shoulder``): its light is the sensor's, whose highlights need no roll-off
    shoulder: Annotated[Optional[Annotated[float, BeforeValidator(_yaml_number), Field(gt=0, le=1)]],
                        Expect("a knee in (0, 1] (1 = the clip) or null (the same as shoulder)")]


class Enhancement(Section):
    gamma_range: Annotated[List[Annotated[float, BeforeValidator(_yaml_number), Field(gt=0)]],
                           Field(min_length=2, max_length=2), Expect("a list [low, high] of two numbers > 0")]
    init_gamma: Num(gt=0)
    per_view: Bool
    # a tone's name: checked against retinexgs.model.tones.TONES by the loader (CHOICES), with the rules each tone
    # sets (a reference), the registry being a layer above
    tone: Annotated[str, Expect("the name of a registered tone")]
    ref_quantile: Annotated[Optional[Annotated[float, BeforeValidator(_yaml_number), Field(gt=0, le=1)]],
                            Expect("a quantile in (0, 1] (1 = the maximum) or null (no normalisation)")]
    shoulder: Num(gt=0, le=1)  # the highlight knee of a tone with one (exposure's); the gamma tones do not read it
    raw: EnhancementRaw  # the camera-raw scenes' own keys

    @model_validator(mode="after")
    def _ordered(self) -> "Enhancement":
        lo, hi = self.gamma_range
        if not lo < hi:
            raise ValueError(f"model.enhancement.gamma_range must be [low, high] with low < high, got [{lo}, {hi}]")
        if not lo <= self.init_gamma <= hi:
            raise ValueError(f"model.enhancement.init_gamma must lie in gamma_range [{lo}, {hi}], "
                             f"got {self.init_gamma}")
        return self


class Model(Section):
    sh_degree: Int(0, 3)
    sh_degree_every: Every
    init_opacity: Num(gt=0, le=1)
    max_init_points: Int(1)
    background: Choice("black", "mean")
    near_fraction: Num(ge=0, le=0.9)
    near_in_training: Bool
    illumination: Illumination
    enhancement: Enhancement


class LossRaw(Section):
    """``loss.raw``: read on camera-raw scenes only (retinexgs.data.capture)."""

    mode: Choice("noise", "relative", "photo")  # the reconstruction: linear light (weighted) or as the photo shown
    unit: Choice("plain", "sigma")
    prior_snr: Num(ge=0)
    spa: Choice("photo", "extended")  # what L_spa compares a raw view's enhanced render with
    r_prior_luma: Num(ge=0, le=1)  # κ: the share of R̂'s luma the reflectance prior supervises (full-size views)
    r_prior_luma_binned: Num(ge=0, le=1)  # κ on views binned by data.downscale > 1


class Loss(Section):
    lambda_ssim: Num(ge=0, le=1)
    w_r: Num(ge=0)
    w_l: Num(ge=0)
    prior_late_from: Step  # schedule: from this step on the priors' weights fall with the views a point has
    prior_late_views: Num(ge=0)  # n0: w_r, w_l × min(1, n0 / n), n training views a point; 0 = off
    w_s: Num(ge=0)
    w_tv: Num(ge=0)
    w_sh: Num(ge=0)
    w_spa: Num(ge=0)
    w_exp: Num(ge=0)
    w_col: Num(ge=0)
    exposure_E: Num(gt=0, le=1)
    exp_on: Choice("illumination", "image")
    exp_patch: Int(0)
    exp_form: Choice("l2", "l1")
    exp_highlight_share: Num(ge=0, le=0.5)
    spa_form: Choice("zero_dce", "paper")
    enhance_scale_invariant: Bool
    sh_reduction: Choice("mean", "sum")
    enhance_from: Step
    enhance_trains_scene: Bool
    rec_domain: Choice("photo", "exposed", "exposed_ssim")
    rec_noise_floor: Bool
    rec_noise_share: Num(gt=0, le=0.9)
    rec_noise_scale: Int(1)
    raw: LossRaw  # the camera-raw scenes' own keys
    w_depth: Num(ge=0)
    depth_edge: Num(ge=0)


class LearningRates(Section):
    means: Num(gt=0)
    means_final: Num(gt=0)
    quats: Num(ge=0)
    scales: Num(ge=0)
    opacities: Num(ge=0)
    sh_dc: Num(ge=0)
    sh_rest: Num(ge=0)
    illumination: Num(ge=0)
    enhancement: Num(ge=0)


class MCMC(Section):
    """``density.mcmc``: the MCMC strategy's knobs (retinexgs/strategy/mcmc.py)."""
    cap_max: Int(1)
    growth: Num(ge=0)
    min_opacity: Num(gt=0, le=1)
    noise_lr: Num(ge=0)
    opacity_reg: Num(ge=0)
    scale_reg: Num(ge=0)


class Density(Section):
    # a strategy's name: checked against retinexgs.strategy.STRATEGIES by the loader (CHOICES), the registry
    # being a layer above
    kind: Annotated[str, Expect("the name of a registered strategy")]
    start: Step
    stop: Step
    every: Every
    grad_threshold: Num(gt=0)
    percent_dense: Num(gt=0)
    prune_opacity: Num(ge=0, le=1)
    reset_opacity_every: EveryOrOff
    last_event: Step
    max_screen_fraction: Num(gt=0)
    max_gaussians: Int(1)
    max_aniso: Annotated[float, BeforeValidator(_yaml_number), Expect("0 (no cap) or a ratio >= 1")]
    mcmc: MCMC

    @model_validator(mode="after")
    def _ratio(self) -> "Density":
        if not (self.max_aniso == 0 or self.max_aniso >= 1):
            raise ValueError(f"density.max_aniso must be 0 (no cap) or a ratio >= 1 (longest axis / shortest), "
                             f"got {self.max_aniso}")
        return self


class Log(Section):
    every: Int(1)
    tensorboard: Bool


class Checkpoint(Section):
    every: Int(1)
    keep: Int(1)


class Eval(Section):
    lpips: Bool  # on by default: LOM papers report LPIPS beside PSNR/SSIM, and the port needs no download
    sheet_max_side: Int(64)  # the contact sheets' panels shrunk to fit: a sheet is for looking


class Train(Section):
    cuda_graphs: Bool
    views_per_rank: Int(1)
    lr_batch_scaling: Choice("sqrt", "linear", "none")
    momentum_batch_scaling: Choice("power", "none")
    stream_views: Choice("auto", "always", "never")
    views_on_device_gb: Num(ge=0)
    views_pinned_gb: Num(ge=0)
    # binning without a host sync (issue 65): the pair buffer is this × the recent pair counts; 0: synced, exact
    pair_margin: Annotated[float, BeforeValidator(_yaml_number), Field(ge=0, allow_inf_nan=False),
                           AfterValidator(_zero_or_at_least_one), Expect("0 (synced binning) or a number >= 1")]
    # [[until, downsample], ...] (retinexgs.train.resolution); YAML lists become the tuples strict mode wants
    resolution: Annotated[List[Tuple[Step, Annotated[StrictInt, Field(ge=1, le=64)]]], BeforeValidator(_pairs),
                          Expect("a list of [until, downsample] pairs: until a fraction of steps 0..1 or a step, "
                                 "downsample an integer 1..64, e.g. [[0.2, 4], [0.5, 2]]; [] for full size")]
    # views of fewer pixels train at full size throughout (retinexgs.train.resolution); 0: every view on the schedule
    resolution_min_pixels: Int(0)


class ConfigSchema(Section):
    """The whole config (``configs/default.yaml`` after every override): what :func:`retinexgs.run.config.load_config`
    returns and every module receives (as :data:`Config`). It is written to ``RUN/config.yaml`` and checkpoints as
    plain data (``model_dump()``), with the run format (:data:`retinexgs.config.versions.FORMAT`) beside it."""

    method: Choice("retinexgs", "3dgs", "pre", "post")
    steps: Annotated[int, Field(ge=1), Expect("a positive integer")]
    seed: Int(0)
    data: Data
    decomposer: Decomposer
    model: Model
    loss: Loss
    lr: LearningRates
    density: Density
    log: Log
    checkpoint: Checkpoint
    eval: Eval
    train: Train

    @model_validator(mode="after")
    def _exposed_needs_a_reference(self) -> "ConfigSchema":
        if self.loss.rec_domain != "photo" and self.model.enhancement.ref_quantile is None:
            # the exposure is 1 / lin(L_ref); without a reference L_ref = 1 and "exposed" would silently be "photo"
            raise ValueError(f"loss.rec_domain '{self.loss.rec_domain}' exposes the photo by 1 / lin(L_ref) and needs "
                             "model.enhancement.ref_quantile (null: no reference); use rec_domain 'photo'")
        return self


def field_expectation(path: Tuple[Any, ...]) -> Tuple[Tuple[str, ...], Optional[str], Optional[type]]:
    """For an error location: (the key path inside the config, what that key expects, its section class when
    the key is a section). Location parts past the last config key (pydantic's union/list members) are dropped."""
    cls: Any = ConfigSchema
    keys: List[str] = []
    expect: Optional[str] = None
    section: Optional[type] = None
    for part in path:
        fields = getattr(cls, "model_fields", None)
        if not isinstance(part, str) or fields is None or part not in fields:
            break
        info = fields[part]
        keys.append(part)
        expect = next((m.text for m in info.metadata if isinstance(m, Expect)), None)
        ann = info.annotation
        section = ann if isinstance(ann, type) and issubclass(ann, BaseModel) else None
        cls = section
    return tuple(keys), expect, section


# The name modules use for the whole validated config.
Config = ConfigSchema
