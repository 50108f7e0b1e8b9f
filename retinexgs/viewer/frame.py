"""The viewer's render callback: a viewer camera and the GUI's settings -> one uint8 frame (torch only).

It reuses the render command's pieces (``render_function`` for the maps, ``render_depth`` / ``depth_range``
for depth) so the viewer shows exactly what ``retinexgs render`` writes, except that ``L`` is shown
normalised (L̂ / L_ref, the illumination the gamma acts on: the raw L̂ of a dark scene is near black) and
depth is colourised.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Callable, ContextManager, Optional, Sequence, Union

import numpy as np
import torch
from torch import Tensor

from retinexgs.data.scene import View
from retinexgs.evaluate.evaluate import to_uint8
from retinexgs.export.renders import depth_range, render_depth
from retinexgs.model.inference import InferenceRenderer
from retinexgs.run.render import render_function
from retinexgs.run.schema import Config
from retinexgs.viewer.camera import ViewerCamera, viewer_to_camera

VIEW_MAPS = ("enhanced", "R", "L", "low", "depth")
BASELINE_MAPS = ("enhanced", "depth")
_KEYS = {"enhanced": "rgb", "R": "R", "low": "S_rec"}

# Depth colour ramp (far -> near): dark blue, purple, orange, pale yellow; piecewise linear between them.
_RAMP = torch.tensor([[0.05, 0.03, 0.25], [0.45, 0.10, 0.55], [0.90, 0.45, 0.15], [1.00, 0.95, 0.70]])


@dataclass(frozen=True)
class FrameSettings:
    """What the GUI controls: the ``map``, ``exposure`` (< 1 brighter, > 1 darker:
    :func:`retinexgs.model.tone.apply_exposure`), ``gamma`` (an absolute gamma replacing the predicted one, or None)
    and the resolution ``scale``."""

    map: str = "enhanced"
    exposure: float = 1.0
    gamma: Optional[float] = None
    scale: float = 1.0


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

    def render(self, cam: ViewerCamera, settings: FrameSettings = FrameSettings()) -> np.ndarray:
        """The frame [H,W,3] uint8 seen from ``cam`` (its size times ``settings.scale``). Baselines have no
        gamma, so exposure and gamma do not apply to them."""
        self.check(settings)
        camera = viewer_to_camera(cam, settings.scale)
        with self._guard(), torch.no_grad():
            if settings.map == "depth":
                return to_uint8(colorize_depth(render_depth(self.model, camera, *self.zrange).cpu()))
            gamma = settings.gamma if self.decomposed else None
            exposure = settings.exposure if self.decomposed and gamma is None else None
            degree = self.degree() if callable(self.degree) else self.degree
            training = self.model.training  # render_function sets eval mode; a live trainer's model gets its back
            try:
                if self._renderer is None:
                    self._renderer = InferenceRenderer(self.model, degree, graphs=not self.live, live=self.live)
                res = render_function(self.model, self.cfg, degree, exposure=exposure, gamma=gamma,
                                      renderer=self._renderer)(camera)
            finally:
                self.model.train(training)
            img = self.model.normalized_illumination(res["L"]) if settings.map == "L" else res[_KEYS[settings.map]]
            return to_uint8(img)
