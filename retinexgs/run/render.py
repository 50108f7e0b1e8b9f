"""How a trained model renders: the camera of a view, the active SH degree, and the render function with its
exposure controls (shared by evaluation, export, the viewer and the benchmarks)."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Dict, List, Optional, Union

import numpy as np

import torch
from torch import Tensor

from retinexgs.data import View
from retinexgs.data.scene import Scene
from retinexgs.errors import UserError
from retinexgs.model.inference import InferenceRenderer
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.model.schedule import build_schedule
from retinexgs.model.white_balance import WhiteBalance, grey_edge_gains, neutral_gains, temperature_matrix
from retinexgs.model.tone import highlight_shoulder, linear_to_srgb, srgb_to_linear, white_balance
from retinexgs.render import Camera
from retinexgs.retinex import decompose, enhance_for_viewing
from retinexgs.config.schema import Config


def active_sh_degree(cfg: Config, step: int) -> int:
    """The SH degree the model renders with after ``step`` steps (it grows by one every sh_degree_every)."""
    return build_schedule(cfg).sh_degree_at(step)


def view_camera(view: View) -> Camera:
    """The renderer's camera for a data-layer view."""
    return Camera(view.world_to_camera(), view.fx, view.fy, view.cx, view.cy, view.width, view.height)


def enhanced_linear(model: RetinexGSModel, cfg: Config, res: Dict) -> Tensor:
    """The linear light (Rec.709 primaries) [H,W,3] that a render's enhanced image ``res["rgb"]`` encodes: for a
    RetinexGS run whose tone has a linear form (``exposure``: k·lin(R̂∘L̂);
    :meth:`~retinexgs.model.RetinexGSModel.tone_linear`) that light before the highlight
    shoulder and the sRGB curve, so it exceeds 1 where the PNG clips or rolls off; otherwise (the gamma tones, the
    baselines) lin(rgb), in [0, 1]. On both scales 1.0 is the PNG's white (with the shoulder off)."""
    if cfg.method == "retinexgs" and "R" in res and "gamma" in res:
        light = model.tone_linear(res["R"], res["L"], res["gamma"].reshape(-1))
        if light is not None:
            return light
    return srgb_to_linear(res["rgb"])


def encode_enhanced(model: RetinexGSModel, cfg: Config, light: Tensor) -> Tensor:
    """The enhanced image (sRGB, [0, 1]) of linear light as :func:`enhanced_linear` returns it: the highlight
    shoulder (RetinexGS, a tone with one: ``exposure``) and the sRGB curve, clipping at white."""
    return linear_to_srgb(highlight_shoulder(light, tone_knee(model, cfg)))


def tone_knee(model: RetinexGSModel, cfg: Config) -> float:
    """The highlight shoulder's knee that :func:`encode_enhanced` applies to this run's light (1: none, the clip)."""
    return float(model.tone.knee(float(model.shoulder))) if cfg.method == "retinexgs" else 1.0


def render_function(model: RetinexGSModel, cfg: Config, degree: int, exposure: Optional[float] = None,
                    gamma: Optional[float] = None, fast: bool = True,
                    renderer: Optional[InferenceRenderer] = None, balance: Optional[Tensor] = None,
                    linear: bool = False) -> Callable[[Union[View, Camera]], Dict]:
    """view (or a renderer camera) -> the model's output maps (``rgb``, and ``R``, ``L``, ``S_rec`` for RetinexGS,
    with ``L_view``: L̂ / L_ref clipped to [0, 1], the one way L̂ is shown, by ``render --maps L``, ``eval``'s
    side-by-side and the viewer); for the post-enhancement baseline, LR3M enhances the render.

    ``fast`` renders through an :class:`~retinexgs.model.inference.InferenceRenderer` (the fused colour kernel,
    CUDA graphs; same images as ``model.render``), built here once or passed as ``renderer`` (the viewer keeps
    one across frames); ``fast=False`` calls ``model.render``.

    ``balance``: a white-balance edit (gains [3] or a 3×3 matrix, :mod:`retinexgs.model.white_balance`) applied
    to the enhanced image's linear light before the shoulder and the sRGB curve; None or exactly the identity
    leaves ``rgb`` as rendered, bit for bit. With ``fast`` and tone ``exposure`` it is applied inside the
    renderer's one tone kernel (:meth:`~retinexgs.model.inference.InferenceRenderer.render`), elsewhere by encoding
    the balanced light again in torch; the two agree to float rounding (tests). ``linear``: the maps also hold
    ``rgb_linear``, that light after the balance (:func:`enhanced_linear`), and ``knee`` (:func:`tone_knee`)."""
    model.eval()
    if fast and renderer is None:
        renderer = InferenceRenderer(model, degree)
    if balance is not None:
        balance = torch.as_tensor(balance, dtype=torch.float32)
        eye = torch.ones(3) if balance.dim() == 1 else torch.eye(3)
        balance = None if torch.equal(balance, eye) else balance
    # The balance inside the renderer's one tone kernel where it can (tone exposure, the default): the frame costs
    # what an unbalanced one does. Elsewhere the light is balanced and encoded again in torch.
    fused_balance = balance if balance is not None and fast and cfg.method != "post" and renderer.can_balance() \
        else None

    def fn(view: Union[View, Camera]) -> Dict:
        camera = view if isinstance(view, Camera) else view_camera(view)
        with torch.no_grad():
            if fast:
                res = renderer.render(camera, exposure=exposure, gamma=gamma, degree=degree, balance=fused_balance)
            else:
                res = model.render(camera, degree, exposure=exposure, gamma=gamma)
            if cfg.method == "post":
                method = cfg.decomposer.method if cfg.decomposer.method != "none" else "lr3m"
                R, L = decompose(res["rgb"].clamp(0, 1), method, **cfg.decomposer.params)
                res = dict(res, rgb=enhance_for_viewing(R, L))
            if "L" in res:  # scene-wide, not per image: one view's L is comparable with another's, videos keep still
                res["L_view"] = model.normalized_illumination(res["L"])
            if linear or (balance is not None and fused_balance is None):
                light = white_balance(enhanced_linear(model, cfg, res), balance)
                res["rgb_linear"] = light
                res["knee"] = tone_knee(model, cfg)
                if balance is not None and fused_balance is None:
                    res["rgb"] = encode_enhanced(model, cfg, light)
        return res

    return fn


AUTO_VIEWS = 32  # auto white balance: at most this many training views, evenly spaced (bounded time, deterministic)


def _find_view(scene: Scene, name: str) -> View:
    views: List[View] = list(scene.train) + list(scene.test) + list(scene.val)
    for v in views:
        if name in (v.name, Path(v.name).stem):
            return v
    shown = ", ".join(Path(v.name).stem for v in views[:8]) + (" ..." if len(views) > 8 else "")
    raise UserError(f"--white-balance pick:{name},...: the scene has no view named {name!r}; its views are "
                    f"{shown} (the image names without suffix, as render writes them)")


def white_balance_of(wb: WhiteBalance, model: RetinexGSModel, cfg: Config, scene: Scene, degree: int,
                     exposure: Optional[float] = None, gamma: Optional[float] = None) -> Optional[np.ndarray]:
    """The balance (float64 gains [3] or a 3×3 matrix; None: as trained) of a parsed ``--white-balance``
    (:mod:`retinexgs.model.white_balance`) for this trained scene: ``auto`` and ``pick`` render it as trained
    (with the same ``exposure``/``gamma``) to measure. UserError for a pick outside the image, on black or on a
    clipped record, or an unknown view."""
    if wb.kind == "as-trained":
        return None
    if wb.kind == "gains":
        return np.asarray(wb.gains, dtype=np.float64)
    if wb.kind == "temp":
        return temperature_matrix(wb.kelvin, wb.tint)
    fn = render_function(model, cfg, degree, exposure=exposure, gamma=gamma, linear=True)
    if wb.kind == "auto":
        views = list(scene.train) or list(scene.test)
        if not views:
            raise UserError("--white-balance auto: the scene has no views to estimate a white balance from")
        views = views[:: max(1, -(-len(views) // AUTO_VIEWS))]
        return np.asarray(grey_edge_gains(fn(v)["rgb_linear"] for v in views), dtype=np.float64)
    if wb.kind == "pick":
        view = _find_view(scene, wb.view)
        if not (0 <= wb.x < view.width and 0 <= wb.y < view.height):
            raise UserError(f"--white-balance {wb.text}: pixel ({wb.x}, {wb.y}) lies outside view {wb.view}, "
                            f"which is {view.width}x{view.height} (X in 0..{view.width - 1}, "
                            f"Y in 0..{view.height - 1})")
        return neutral_at(fn(view), wb.x, wb.y, wb.text)
    raise ValueError(f"unknown white balance kind {wb.kind!r}")


def neutral_at(res: Dict, x: int, y: int, where: str):
    """Gains (G/R, 1, G/B, float64 [3]) that make pixel column ``x``, row ``y`` of a render neutral; ``res`` is
    ``render_function(..., linear=True)``'s maps of that view as trained; ``--white-balance pick``
    (:func:`white_balance_of`) and the viewer's eyedropper alike. UserError (naming ``where``) when the pixel is
    clipped in the reconstructed photo (its hue is lost) or black."""
    record = res["R"] * res["L"] if "R" in res and "L" in res else res["rgb"]
    if float(record[y, x].max()) >= 0.999:  # the photos were clipped there: their hue is lost
        raise UserError(f"--white-balance {where}: the picked pixel is clipped (a channel at white in the "
                        "reconstructed photo), so its colour is not the light's; pick a neutral that is not "
                        "blown out")
    return np.asarray(neutral_gains(res["rgb_linear"][y, x].double().cpu().tolist(), where))
