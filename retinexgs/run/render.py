"""How a trained model renders: the camera of a view, the active SH degree, and the render function with its
exposure controls (shared by evaluation, export, the viewer and the benchmarks)."""
from __future__ import annotations

from typing import Callable, Dict, Optional, Union

import torch

from retinexgs.data import View
from retinexgs.model.inference import InferenceRenderer
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.model.schedule import build_schedule
from retinexgs.render import Camera
from retinexgs.retinex import decompose, enhance_for_viewing
from retinexgs.run.schema import Config


def active_sh_degree(cfg: Config, step: int) -> int:
    """The SH degree the model renders with after ``step`` steps (it grows by one every sh_degree_every)."""
    return build_schedule(cfg).sh_degree_at(step)


def view_camera(view: View) -> Camera:
    """The renderer's camera for a data-layer view."""
    return Camera(view.world_to_camera(), view.fx, view.fy, view.cx, view.cy, view.width, view.height)


def render_function(model: RetinexGSModel, cfg: Config, degree: int, exposure: Optional[float] = None,
                    gamma: Optional[float] = None, fast: bool = True,
                    renderer: Optional[InferenceRenderer] = None) -> Callable[[Union[View, Camera]], Dict]:
    """view (or a renderer camera) -> the model's output maps (``rgb``, and ``R``, ``L``, ``S_rec`` for RetinexGS,
    with ``L_view``: L̂ / L_ref clipped to [0, 1], the one way L̂ is shown, by ``render --maps L``, ``eval``'s
    side-by-side and the viewer); for the post-enhancement baseline, LR3M enhances the render.

    ``fast`` renders through an :class:`~retinexgs.model.inference.InferenceRenderer` (the fused colour kernel,
    CUDA graphs; same images as ``model.render``), built here once or passed as ``renderer`` (the viewer keeps
    one across frames); ``fast=False`` calls ``model.render``."""
    model.eval()
    if fast and renderer is None:
        renderer = InferenceRenderer(model, degree)

    def fn(view: Union[View, Camera]) -> Dict:
        camera = view if isinstance(view, Camera) else view_camera(view)
        with torch.no_grad():
            if fast:
                res = renderer.render(camera, exposure=exposure, gamma=gamma, degree=degree)
            else:
                res = model.render(camera, degree, exposure=exposure, gamma=gamma)
            if cfg.method == "post":
                method = cfg.decomposer.method if cfg.decomposer.method != "none" else "lr3m"
                R, L = decompose(res["rgb"].clamp(0, 1), method, **cfg.decomposer.params)
                res = dict(res, rgb=enhance_for_viewing(R, L))
            if "L" in res:  # scene-wide, not per image: one view's L is comparable with another's, videos keep still
                res["L_view"] = model.normalized_illumination(res["L"])
        return res

    return fn
