"""Re-denoising the training views with the model's own render as the pilot (issue 64 item 1, ``decomposer.redenoise_at``).

A single-view denoiser at SNR ≈ 1 leaves low-frequency colour blotches in the 2D priors; the 3D model's render of a
view averages every view that saw the scene, so it is a far better pilot. At each step of ``decomposer.redenoise_at``
every training view is filtered with Wiener gains taken from its render (:func:`retinexgs.retinex.denoise.pilot_wiener`:
what the render says is signal survives, what it says is noise goes), decomposed again, and its 2D priors R, L
replaced; the reconstruction term keeps the view's own unbiased light. Measured on a trained run before any training
change by ``experiments/pilot_wiener_study.py``. With ``decomposer.redenoise_source: views`` a view is instead
averaged with its neighbours warped in along the model's depth (:mod:`retinexgs.train.view_warp`), then denoised at
the average's noise (``experiments/warp_pilot_study.py``).
"""
from __future__ import annotations

from typing import Callable, List, Optional, Sequence

import torch
from torch import Tensor

from retinexgs.config.schema import Config
from retinexgs.data import Scene
from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear, srgb_to_linear_extended
from retinexgs.errors import UserError
from retinexgs.model.schedule import at_step
from retinexgs.retinex import decompose
from retinexgs.retinex.denoise import DenoiseParams, NoiseModel, denoise_linear, pilot_wiener
from retinexgs.train.view_setup import denoise_params, views_noise
from retinexgs.train.view_warp import WarpSource, neighbours, warp_average
from retinexgs.train.views import TrainView

# decomposer.redenoise_source views: neighbours averaged into each view. 16: on the fox-dark proxy's training views
# the average denoised scored 21.39 / 21.57 / 21.31 dB with 8 / 16 / 32 (experiments/warp_pilot_study.py).
NEIGHBOURS = 16

Render = Callable[[TrainView, bool], dict]  # (view, with depth) -> the model's maps (S_rec; out with depth, alpha)


def redenoise_steps(cfg: Config) -> List[int]:
    """The steps after which the views are re-denoised (``decomposer.redenoise_at`` in steps), sorted, in (0, steps)."""
    return sorted({s for s in (at_step(v, cfg.steps) for v in cfg.decomposer.redenoise_at) if 0 < s < cfg.steps})


def check_redenoise(cfg: Config, streamed: bool) -> None:
    """UserError (one line) where ``decomposer.redenoise_at`` cannot run: it replaces 2D priors (RetinexGS with a
    decomposer) of views held on the device (not streamed)."""
    if not redenoise_steps(cfg):
        return
    if cfg.method != "retinexgs" or cfg.decomposer.method == "none":
        raise UserError("decomposer.redenoise_at re-denoises the 2D priors: it needs method retinexgs and a "
                        "decomposer (decomposer.method lr3m or lime)")
    if streamed:
        raise UserError("decomposer.redenoise_at replaces the views' priors on the device: the views are streamed "
                        "here, set train.stream_views=never (or drop decomposer.redenoise_at)")


def _light(tv: TrainView, unclipped: bool) -> Tensor:
    S = tv.S.float()
    return srgb_to_linear_extended(S) if unclipped else srgb_to_linear(S)


def _replace_priors(tv: TrainView, clean: Tensor, cfg: Config) -> None:
    """The view's priors R, L from the decomposition of ``clean`` linear light [H,W,3]."""
    dcfg = cfg.decomposer
    with torch.no_grad():
        R, L = decompose(linear_to_srgb(clean.clamp(0.0, 1.0)).float(), dcfg.method, **dict(dcfg.params))
    tv.R = R.to(device=tv.R.device, dtype=tv.R.dtype).reshape(tv.R.shape)
    tv.L = L.to(device=tv.L.device, dtype=tv.L.dtype).reshape(tv.L.shape)
    tv.packed = tv.edges = None  # built again from the new priors on the view's next step


def _single_method(cfg: Config) -> str:
    """The single-view denoiser's method a re-denoising uses (``chroma`` where the config's is auto or none)."""
    method = cfg.decomposer.denoise
    return method if method in ("nlm", "chroma") else "chroma"


def redenoise_priors(views: Sequence[TrainView], render: Render, noise: NoiseModel,
                     unclipped: bool, cfg: Config, params: Optional[DenoiseParams] = None) -> None:
    """Replace each view's priors R, L by the decomposition of its light re-denoised with the model's help
    (``decomposer.redenoise_source``): ``render`` filtered with Wiener gains from ``render(view, False)["S_rec"]``
    (R̂∘L̂, sRGB-encoded like S); ``views`` its neighbours warped in through the model's depth and averaged
    (:func:`views_average`). ``unclipped``: S is a raw view's unclipped encoding. ``params``: the single-view
    denoiser's settings (the scene's, :func:`denoise_params`; None: the config's alone)."""
    dcfg = cfg.decomposer
    if params is None:
        params = DenoiseParams.from_mapping(dcfg.denoise_params)
    if dcfg.redenoise_source == "views":
        for tv, clean in zip(views, views_average(views, render, noise, unclipped, cfg)):
            _replace_priors(tv, clean, cfg)
        return
    for tv in views:
        light = _light(tv, unclipped)
        with torch.no_grad():
            pilot = srgb_to_linear(render(tv, False)["S_rec"].float().clamp(0.0, 1.0))
            chroma = None
            if dcfg.redenoise_chroma == "denoiser":  # the single-view denoiser's chroma, the render's luma
                chroma = denoise_linear(light, noise, _single_method(cfg), params, backend=dcfg.denoise_backend)
            clean = pilot_wiener(light, pilot, noise, chroma=chroma)
        _replace_priors(tv, clean, cfg)


def views_average(views: Sequence[TrainView], render: Render, noise: NoiseModel, unclipped: bool,
                  cfg: Config) -> List[Tensor]:
    """Each view's light [H,W,3] averaged with its :data:`NEIGHBOURS` nearest views warped in through the model's
    depth (:func:`retinexgs.train.view_warp.warp_average`), then through the single-view denoiser at the average's
    noise (the view's ÷ the median count averaged) with the config's settings at full strength: the average has
    already done what the views per point do for the luma (:func:`denoise_params` lightens it for that)."""
    dcfg = cfg.decomposer
    params = DenoiseParams.from_mapping(dcfg.denoise_params)
    sources = []
    with torch.no_grad():
        for tv in views:
            out = render(tv, True)["out"]
            alpha = out.alpha[..., 0].float()
            sources.append(WarpSource(tv.camera, _light(tv, unclipped), out.depth[..., 0].float() /
                                      alpha.clamp_min(1e-6), alpha))
        cameras = [s.camera for s in sources]
        result = []
        for i, me in enumerate(sources):
            avg, count = warp_average(me, [sources[j] for j in neighbours(cameras, i, NEIGHBOURS)])
            n = float(count.median())
            averaged = NoiseModel(tuple(a / n for a in noise.a), tuple(b / n for b in noise.b))
            result.append(denoise_linear(avg, averaged, _single_method(cfg), params,
                                         backend=dcfg.denoise_backend).to(avg))
    return result


class Redenoise:
    """``decomposer.redenoise_at`` for one run: its steps, the views' noise and how S encodes light."""

    def __init__(self, steps: List[int], noise: NoiseModel, unclipped: bool,
                 params: Optional[DenoiseParams] = None) -> None:
        self.steps, self.noise, self.unclipped, self.params = steps, noise, unclipped, params

    @classmethod
    def for_run(cls, cfg: Config, scene: Scene, streamed: bool, device: str) -> Optional["Redenoise"]:
        """None where ``decomposer.redenoise_at`` is empty; UserError (one line) where it cannot run
        (:func:`check_redenoise`)."""
        steps = redenoise_steps(cfg)
        if not steps:
            return None
        check_redenoise(cfg, streamed)
        noise = views_noise(list(scene.train), cfg, device)
        if noise is None:
            raise UserError("decomposer.redenoise_at needs the views' noise, which could not be measured (no flat "
                            "area in any view): drop decomposer.redenoise_at")
        return cls(steps, noise, scene.capture.unclipped, denoise_params(cfg, scene.views_per_point()))

    def due(self, step: int, resumed_from: Optional[int] = None) -> bool:
        """Whether the views are re-denoised after ``step``; with ``resumed_from`` (a resumed run's first step):
        whether the priors the run had at that step were re-denoised ones (the views are read fresh on resume)."""
        if resumed_from is not None:
            return any(s < resumed_from for s in self.steps)
        return step in self.steps

    def run(self, views: Sequence[TrainView], render: Render, cfg: Config) -> None:
        redenoise_priors(views, render, self.noise, self.unclipped, cfg, self.params)
