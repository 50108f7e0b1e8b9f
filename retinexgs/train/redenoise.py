"""Re-denoising the training views with the model's own render as the pilot (issue 64 item 1, ``decomposer.redenoise_at``).

A single-view denoiser at SNR ≈ 1 leaves low-frequency colour blotches in the 2D priors; the 3D model's render of a
view averages every view that saw the scene, so it is a far better pilot. At each step of ``decomposer.redenoise_at``
every training view is filtered with Wiener gains taken from its render (:func:`retinexgs.retinex.denoise.pilot_wiener`:
what the render says is signal survives, what it says is noise goes), decomposed again, and its 2D priors R, L
replaced; the reconstruction term keeps the view's own unbiased light. Measured on a trained run before any training
change by ``experiments/pilot_wiener_study.py``.
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
from retinexgs.train.views import TrainView


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


def redenoise_priors(views: Sequence[TrainView], render: Callable[[TrainView], Tensor], noise: NoiseModel,
                     unclipped: bool, cfg: Config, params: Optional[DenoiseParams] = None) -> None:
    """Replace each view's priors R, L by the decomposition of its light filtered with Wiener gains from
    ``render(view)`` (R̂∘L̂, sRGB-encoded like S). ``unclipped``: S is a raw view's unclipped encoding. ``params``:
    the single-view denoiser's settings (the scene's, :func:`denoise_params`; None: the config's alone)."""
    dcfg = cfg.decomposer
    if params is None:
        params = DenoiseParams.from_mapping(dcfg.denoise_params)
    for tv in views:
        S = tv.S.float()
        light = srgb_to_linear_extended(S) if unclipped else srgb_to_linear(S)
        with torch.no_grad():
            pilot = srgb_to_linear(render(tv).float().clamp(0.0, 1.0))
            chroma = None
            if dcfg.redenoise_chroma == "denoiser":  # the single-view denoiser's chroma, the render's luma
                method = dcfg.denoise if dcfg.denoise in ("nlm", "chroma") else "chroma"
                chroma = denoise_linear(light, noise, method, params, backend=dcfg.denoise_backend)
            clean = pilot_wiener(light, pilot, noise, chroma=chroma).clamp(0.0, 1.0)
            R, L = decompose(linear_to_srgb(clean).float(), dcfg.method, **dict(dcfg.params))
        tv.R = R.to(device=tv.R.device, dtype=tv.R.dtype).reshape(tv.R.shape)
        tv.L = L.to(device=tv.L.device, dtype=tv.L.dtype).reshape(tv.L.shape)
        tv.packed = tv.edges = None  # built again from the new priors on the view's next step


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

    def run(self, views: Sequence[TrainView], render: Callable[[TrainView], Tensor], cfg: Config) -> None:
        redenoise_priors(views, render, self.noise, self.unclipped, cfg, self.params)
