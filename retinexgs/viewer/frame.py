"""The viewer's render callback: a viewer camera and the GUI's settings -> one uint8 frame (torch only).

It reuses the render command's pieces (``render_function`` for the maps, ``render_depth`` / ``depth_range``
for depth) so the viewer shows exactly what ``retinexgs render`` writes, except that ``L`` is shown
normalised (L̂ / L_ref, the illumination the gamma acts on: the raw L̂ of a dark scene is near black) and
depth is colourised.

The white balance (issue 53) takes the forms of ``render --white-balance`` (:mod:`retinexgs.model.white_balance`)
and goes through the render command's own functions (:func:`retinexgs.run.render.white_balance_of` for the
numbers, ``render_function(..., balance=)`` for the frame), so a frame shows what ``render`` writes for the same
form. The eyedropper (:meth:`FrameRenderer.pick_neutral`) turns a pixel of the current view into ``gains:``.
The highlight-shoulder switch off encodes the same linear light with the clip at white instead of the run's knee.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Callable, ContextManager, Dict, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from retinexgs.data.scene import View
from retinexgs.evaluate.evaluate import to_uint8
from retinexgs.export.renders import depth_range, render_depth
from retinexgs.errors import UserError
from retinexgs.model.inference import InferenceRenderer
from retinexgs.model.tone import linear_to_srgb
from retinexgs.model.white_balance import WhiteBalance, describe_balance, parse_white_balance
from retinexgs.run.render import neutral_at, render_function, white_balance_of
from retinexgs.config.schema import Config
from retinexgs.viewer.camera import ViewerCamera, viewer_to_camera

VIEW_MAPS = ("enhanced", "R", "L", "low", "depth")
BASELINE_MAPS = ("enhanced", "depth")
_KEYS = {"enhanced": "rgb", "R": "R", "low": "S_rec"}

# Depth colour ramp (far -> near): dark blue, purple, orange, pale yellow; piecewise linear between them.
_RAMP = torch.tensor([[0.05, 0.03, 0.25], [0.45, 0.10, 0.55], [0.90, 0.45, 0.15], [1.00, 0.95, 0.70]])


@dataclass(frozen=True)
class FrameSettings:
    """What the GUI controls: the ``map``, ``exposure`` (< 1 brighter, > 1 darker:
    :func:`retinexgs.model.tone.apply_exposure`), ``gamma`` (an absolute gamma replacing the predicted one, or None),
    the resolution ``scale``, ``white_balance`` (a ``render --white-balance`` form: as-trained, auto, gains:R,G,B
    or temp:KELVIN[,TINT]; the eyedropper gives gains) and ``shoulder`` (False: the enhanced image clips at white
    instead of rolling its highlights off at the run's knee)."""

    map: str = "enhanced"
    exposure: float = 1.0
    gamma: Optional[float] = None
    scale: float = 1.0
    white_balance: str = "as-trained"
    shoulder: bool = True


def colorize_depth(disp: Tensor) -> Tensor:
    """[H,W,1] inverse depth in [0,1] (0 = far or empty) -> [H,W,3] colours on the ramp; empty stays black."""
    x = disp[..., 0].float().clamp(0, 1) * (len(_RAMP) - 1)
    i = x.floor().long().clamp(max=len(_RAMP) - 2)
    w = (x - i)[..., None]
    rgb = _RAMP[i] * (1 - w) + _RAMP[i + 1] * w
    return torch.where(disp > 0, rgb, torch.zeros_like(rgb))


def _positive(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


class FrameRenderer:
    """Renders a model for the viewer. ``views``: the training views (they fix the depth range, so the depth
    colours do not change as the camera moves). ``degree``: the SH degree, or a function giving it (a model
    in training). ``guard``: a context manager factory held while a frame renders (a trainer's step gate, so
    no frame sees a half-updated model); by default a lock, so frames render one at a time."""

    def __init__(self, model, cfg: Config, degree: Union[int, Callable[[], int]], views: Sequence[View] = (),
                 guard: Optional[Callable[[], ContextManager]] = None) -> None:
        self.model, self.cfg, self.degree = model, cfg, degree
        self.decomposed = cfg.method == "retinexgs"
        self.maps = VIEW_MAPS if self.decomposed else BASELINE_MAPS
        self.zrange = depth_range(model, views) if views else (0.1, 10.0)
        self._guard = guard
        # One inference renderer across frames (packed weights, CUDA graphs); a live trainer's model changes every
        # step, so its renderer repacks per frame and skips graphs (their capture would cost more than it saves).
        self.live = guard is not None or callable(degree)
        self._renderer: Optional[InferenceRenderer] = None
        self.views = list(views)
        # auto's gains per (exposure, gamma, degree): measured over the training views once, not per frame. A live
        # trainer's scene drifts from them; choosing auto again re-measures (forget_auto).
        self._auto: Dict[Tuple, object] = {}
        self.balance_text = "white balance as-trained: none (as trained)"  # the last enhanced frame's, as render says
        # the shoulder switch exists where the run has one: a tone with a highlight knee below 1 (exposure's)
        self.has_shoulder = self.decomposed and model.tone.knee(float(model.shoulder)) < 1.0
        if guard is None:
            lock = threading.Lock()
            self._guard = lambda: lock

    def check(self, settings: FrameSettings) -> None:
        """ValueError naming the bad setting (unknown or unavailable map, exposure/gamma not positive)."""
        if settings.map not in self.maps:
            raise ValueError(f"map {settings.map!r} is not available for this run; choose from {', '.join(self.maps)}")
        _positive("exposure", settings.exposure)
        if settings.gamma is not None:
            _positive("gamma", settings.gamma)
        self.white_balance(settings)

    def white_balance(self, settings: FrameSettings) -> WhiteBalance:
        """The parsed ``settings.white_balance``; ValueError (as for a bad exposure) for a bad form, or for
        ``pick:`` (the viewer picks with the eyedropper, :meth:`pick_neutral`, which gives gains)."""
        try:
            wb = parse_white_balance(settings.white_balance)
        except UserError as exc:
            raise ValueError(str(exc)) from None
        if wb.kind == "pick":
            raise ValueError("the viewer picks a neutral with its eyedropper (pick_neutral), which gives gains:R,G,B")
        if wb.kind == "auto" and not self.views:
            raise ValueError("white balance auto needs the training views, and this viewer was given none")
        return wb

    def forget_auto(self) -> None:
        """Drop the cached ``auto`` gains (a live trainer's scene has moved on): the next auto frame re-measures."""
        self._auto.clear()

    def _balance(self, wb: WhiteBalance, exposure: Optional[float], gamma: Optional[float], degree: int):
        """The balance of ``wb`` (None: as trained), through the render command's :func:`white_balance_of`."""
        if wb.kind != "auto":
            return white_balance_of(wb, self.model, self.cfg, None, degree, exposure, gamma)
        key = (exposure, gamma, degree)
        if key not in self._auto:
            scene = SimpleNamespace(train=self.views, test=[], val=[])  # what white_balance_of reads of a scene
            self._auto[key] = white_balance_of(wb, self.model, self.cfg, scene, degree, exposure, gamma)
        return self._auto[key]

    def pick_neutral(self, cam: ViewerCamera, settings: FrameSettings, u: float,
                     v: float) -> Tuple[float, float, float]:
        """The eyedropper: gains (G/R, 1, G/B) that make neutral the pixel at ``u``, ``v`` (0..1 from the top left,
        a viewer click's screen position) of the enhanced frame as trained at ``settings``' exposure or gamma,
        as ``render --white-balance pick:`` computes them. UserError when that pixel is black or clipped."""
        self.check(settings)
        if not (math.isfinite(u) and math.isfinite(v)):
            raise ValueError(f"the click's screen position must be finite, got {u!r}, {v!r}")
        camera = viewer_to_camera(cam, settings.scale)
        x = min(max(int(u * camera.width), 0), camera.width - 1)
        y = min(max(int(v * camera.height), 0), camera.height - 1)
        with self._guard(), torch.no_grad():
            gamma = settings.gamma if self.decomposed else None
            exposure = settings.exposure if self.decomposed and gamma is None else None
            degree = self.degree() if callable(self.degree) else self.degree
            training = self.model.training
            try:
                res = render_function(self.model, self.cfg, degree, exposure=exposure, gamma=gamma, fast=False,
                                      linear=True)(camera)
            finally:
                self.model.train(training)
        return neutral_at(res, x, y, f"pick (the viewer's eyedropper at pixel {x}, {y})")

    def render(self, cam: ViewerCamera, settings: FrameSettings = FrameSettings()) -> np.ndarray:
        """The frame [H,W,3] uint8 seen from ``cam`` (its size times ``settings.scale``). Baselines have no
        gamma, so exposure and gamma do not apply to them. The white balance and the shoulder switch change the
        enhanced map only (R̂, L̂, low and depth are the scene's, not the edit's)."""
        self.check(settings)
        wb = self.white_balance(settings)
        camera = viewer_to_camera(cam, settings.scale)
        with self._guard(), torch.no_grad():
            if settings.map == "depth":
                return to_uint8(colorize_depth(render_depth(self.model, camera, *self.zrange).cpu()))
            gamma = settings.gamma if self.decomposed else None
            exposure = settings.exposure if self.decomposed and gamma is None else None
            degree = self.degree() if callable(self.degree) else self.degree
            training = self.model.training  # render_function sets eval mode; a live trainer's model gets its back
            try:
                enhanced = settings.map == "enhanced"
                balance = self._balance(wb, exposure, gamma, degree) if enhanced else None
                if enhanced:
                    self.balance_text = describe_balance(wb, balance)
                clip = enhanced and self.has_shoulder and not settings.shoulder
                if self._renderer is None:
                    self._renderer = InferenceRenderer(self.model, degree, graphs=not self.live, live=self.live)
                res = render_function(self.model, self.cfg, degree, exposure=exposure, gamma=gamma,
                                      renderer=self._renderer, balance=balance, linear=clip)(camera)
            finally:
                self.model.train(training)
            if clip:  # the shoulder off: the same linear light, clipped at white by the sRGB curve
                res["rgb"] = linear_to_srgb(res["rgb_linear"])
            img = self.model.normalized_illumination(res["L"]) if settings.map == "L" else res[_KEYS[settings.map]]
            return to_uint8(img)
