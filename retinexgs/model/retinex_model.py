"""The full RetinexGS model: reflectance Gaussians + illumination field + EnhancementNet, rendered in one pass.

Per view: reflectance colours (SH, albedo) and illumination (MLP on PE(x), PE(d)) of every Gaussian are
rasterized together as 6 channels, giving R̂ and L̂; the low-light reconstruction is R̂∘L̂ and the enhanced
output S_enh is a tone map of R̂, L̂ with g predicted by the EnhancementNet from L̂/L_ref (one g per image by
default): the default's longer exposure srgb(k·lin(R̂∘L̂)), k = lin(L_ref)^(−1/g), or the paper's
clip(R̂∘(L̂/L_ref)^g, 0, 1) (``model.enhancement.tone``, :mod:`retinexgs.model.tones`).

Why L_ref: L̂ lives in the photos' exposure scale (the 2D prior L is "in the scale of S", ~0.1-0.3 for a dark
scene), and a gamma curve only brightens with the right contrast on an illumination normalised to [0, 1]
(1 = the brightest light in the scene) — the same normalisation as LR3M's display rule R∘(L/max L)^{1/γ}.
Without it no g reaches a normal exposure: on fox-dark's LR3M maps the best R∘L^g is 17.8 dB against the
normal-light photo, R∘(L/L_ref)^g reaches 25 dB. L_ref is one scene-wide constant (a buffer saved with the
model: the median over training views of a quantile of the 2D prior L — by default its maximum, as in LR3M's
rule; ``model.enhancement.ref_quantile`` — set by the trainer), not a per-view value, so the enhancement
stays 3D-consistent. With ``ref_quantile: null`` L_ref = 1 (configs/paper.yaml: L_enh = L̂^g as written).
The plain-3DGS baselines use the same Gaussians with 3 colour channels and no illumination or enhancement.
"""
from __future__ import annotations

import copy
from typing import Any, Callable, Dict, List, Optional, Tuple

import torch
from torch import Tensor, nn

from retinexgs.config.schema import Enhancement, Model
from retinexgs.data.capture import PHOTO, Capture
from retinexgs.model.enhancement import EnhancementNet
from retinexgs.model.gaussians import GaussianModel, sh_colors
from retinexgs.model.illumination import IlluminationField
from retinexgs.model.illumination_kernel import illumination_at
from retinexgs.model.near_plane import with_near
from retinexgs.model.tones import Tone, get_tone
from retinexgs.render import Camera, rasterize_gaussians
from retinexgs.render.pair_budget import PairBudget


def gaussian_channels(means: Tensor, sh_dc: Tensor, sh_rest: Tensor, center: Tensor, degree: int,
                      illumination: Optional[IlluminationField] = None) -> Tensor:
    """The per-Gaussian channels a render rasterizes, [N,3] or [N,6]: the SH colour max(SH(dir) + 0.5, 0) of
    degree ``degree`` (the albedo R̂) and, with ``illumination``, the illumination field at each centre seen
    from ``center`` (L̂). A function of the tensors, so that the trainer can capture it in a CUDA graph."""
    colors = sh_colors(means, sh_dc, sh_rest, center, degree)
    if illumination is None:
        return colors
    illum = illumination_at(illumination, means, center)  # two kernels on the GPU (illumination_kernel.py)
    return torch.cat([colors, illum.to(colors)], dim=-1)


class GaussianChannels(nn.Module):
    """:func:`gaussian_channels` as a module holding the illumination field (its parameters) at one SH degree:
    the callable the trainer graphs (``torch.cuda.make_graphed_callables`` takes a module's parameters)."""

    def __init__(self, degree: int, illumination: Optional[IlluminationField]) -> None:
        super().__init__()
        self.degree = int(degree)
        self.illumination = illumination

    def forward(self, means: Tensor, sh_dc: Tensor, sh_rest: Tensor, center: Tensor) -> Tensor:
        return gaussian_channels(means, sh_dc, sh_rest, center, self.degree, self.illumination)


class RetinexGSModel(nn.Module):
    """Gaussians (+ illumination field and EnhancementNet when ``decomposed``)."""

    def __init__(self, gaussians: GaussianModel, model_cfg: Model, decomposed: bool = True,
                 capture: Capture = PHOTO) -> None:
        super().__init__()
        self.gaussians = gaussians
        self.decomposed = decomposed
        self.capture = capture  # the scene's kind of capture: it sets the tone's knee (model.enhancement.raw.shoulder)
        if decomposed:
            il = model_cfg.illumination
            self.illumination = IlluminationField(pos_freqs=il.pos_freqs, dir_freqs=il.dir_freqs, hidden=il.hidden,
                                                  depth=il.depth, dir_hidden=il.dir_hidden,
                                                  init_value=il.init_value, view_dependent=il.view_dependent)
            self._set_enhancement(model_cfg.enhancement)
            self.register_buffer("illum_ref", torch.ones(()))  # L_ref; set by the trainer from the 2D priors
        # model.background "mean": uncovered pixels show [6] channel values (R̂ then L̂) that the trainer sets from
        # the training views' priors, instead of black; a buffer, so checkpoints carry it. RetinexGS's only: the
        # 3DGS baselines stay as published (black).
        self.has_background = decomposed and model_cfg.background == "mean"
        if self.has_background:
            self.register_buffer("background", torch.zeros(6))
        # model.near_fraction: every render draws nothing closer to its camera than ``near`` (model/near_plane.py),
        # set by the trainer from the training views' content; a buffer, so checkpoints carry it. RetinexGS's only.
        self.has_near = decomposed and float(model_cfg.near_fraction) > 0
        if self.has_near:
            self.register_buffer("near", torch.zeros(()))
        self._near_cache = (None, 0.0)  # (the buffer's version, its value): no device sync per frame
        self._near_cameras: Dict[int, Tuple[Camera, float, Camera]] = {}  # id -> (camera, near, its raised copy)

    @torch.no_grad()
    def initialise_levels(self, statistics: Callable[[], Any], near: Callable[[], float]) -> None:
        """Set the levels a new model starts from (a checkpoint holds its own): L_ref, the median over the views of
        the prior L's ``ref_quantile`` quantile, and the mean background (the views' mean R̂ and L̂: the best
        constant where no view sees anything), both from ``statistics()`` (the training views' ViewStatistics),
        and the near plane from ``near()``; each only where this model has it."""
        stats = statistics() if self.decomposed or self.has_background else None
        if self.decomposed:
            self.illum_ref.fill_(stats.illumination_reference())
        if self.has_background:
            self.background.copy_(stats.mean_background())
        if self.has_near:
            self.near.fill_(near())

    def param_groups(self, lr: Any, extent: float) -> List[Dict[str, Any]]:
        """The optimiser's parameter groups, one per Gaussian parameter (named as the strategy's edits expect) and
        one per network, at the config's learning rates ``lr`` (``cfg.lr``; the means' scaled by the scene's
        ``extent``)."""
        g = self.gaussians
        groups = [{"params": [g.means], "lr": lr.means * extent, "name": "means"},
                  {"params": [g.quats], "lr": lr.quats, "name": "quats"},
                  {"params": [g.log_scales], "lr": lr.scales, "name": "log_scales"},
                  {"params": [g.opacity_logits], "lr": lr.opacities, "name": "opacity_logits"},
                  {"params": [g.sh_dc], "lr": lr.sh_dc, "name": "sh_dc"},
                  {"params": [g.sh_rest], "lr": lr.sh_rest, "name": "sh_rest"}]
        if self.decomposed:
            groups += [{"params": list(self.illumination.parameters()), "lr": lr.illumination, "name": "illumination"},
                       {"params": list(self.enhancement.parameters()), "lr": lr.enhancement, "name": "enhancement"}]
        return groups

    def near_plane(self) -> float:
        """The depth below which no Gaussian is drawn (0: none), read once per change of the buffer."""
        if not self.has_near:
            return 0.0
        key = (self.near.data_ptr(), self.near._version)
        if self._near_cache[0] != key:
            self._near_cache = (key, float(self.near))
        return self._near_cache[1]

    def camera_for(self, camera: Camera) -> Camera:
        """``camera`` as this model renders it: its near plane raised to :meth:`near_plane`."""
        near = self.near_plane()
        if near <= 0:
            return camera
        hit = self._near_cameras.get(id(camera))
        if hit is not None and hit[0] is camera and hit[1] == near:  # a frame costs no copy of a camera it has seen
            return hit[2]
        if len(self._near_cameras) >= 256:
            self._near_cameras.clear()
        raised = with_near(camera, near)
        self._near_cameras[id(camera)] = (camera, near, raised)
        return raised

    def _set_enhancement(self, enh: Enhancement) -> None:
        """A fresh EnhancementNet and the tone form from a ``model.enhancement`` section (its ``ref_quantile`` is
        the trainer's: it sets illum_ref)."""
        self.tone = enh.tone  # the registered Tone of the name (the ``tone`` property)
        self.shoulder = self.capture.knee(enh)  # the highlight knee of a tone with a shoulder (1: the clip)
        self.enhancement = EnhancementNet(channels=3, gamma_range=tuple(enh.gamma_range), init_gamma=enh.init_gamma,
                                          per_view=enh.per_view)

    @property
    def tone(self) -> Tone:
        """The tone form (``model.enhancement.tone``: a :class:`~retinexgs.model.tones.Tone` of the registry);
        assign a name or a Tone."""
        return self._tone

    @tone.setter
    def tone(self, value) -> None:
        self._tone = get_tone(value)

    def with_enhancement(self, enh_cfg: Enhancement) -> "RetinexGSModel":
        """A model that shares this one's Gaussians, illumination field and L_ref (not copied, not trained here)
        with a fresh, untrained enhancement from ``enh_cfg`` (a ``model.enhancement`` section) on their device."""
        other = copy.copy(self)
        other._modules = dict(self._modules)  # its own module table: its new net leaves this model's in place
        other._set_enhancement(enh_cfg)
        other.enhancement.to(self.illum_ref.device)
        return other

    def normalized_illumination(self, L: Tensor) -> Tensor:
        """L̂ / L_ref clamped to [0, 1]: the illumination the gamma acts on (any shape)."""
        return (L / self.illum_ref.to(L)).clamp(0.0, 1.0)

    def enhance(self, R: Tensor, L: Tensor, exposure: Optional[float] = None,
                gamma: Optional[float] = None) -> Dict[str, Tensor]:
        """S_enh for [H,W,3] maps ``R``, ``L`` in the model's tone form (:mod:`retinexgs.model.tones`); returns
        ``rgb``, ``L_enh`` (the enhanced light) [H,W,3] and ``gamma`` (flattened). ``exposure`` adjusts the
        predicted g (< 1 brighter: :meth:`retinexgs.model.tones.Tone.apply_exposure`); ``gamma`` replaces it."""
        g = self.enhance_gamma(L, exposure, gamma)
        rgb, L_enh = self.tone_map(R, L, g)
        return {"rgb": rgb, "L_enh": L_enh, "gamma": g}

    def enhance_gamma(self, L: Tensor, exposure: Optional[float] = None,
                      gamma: Optional[float] = None) -> Tensor:
        """The g (flattened, [C]) that :meth:`enhance` tones with, for the [H,W,3] light ``L``."""
        L_bchw = self.normalized_illumination(L).permute(2, 0, 1).unsqueeze(0)
        g = self.predict_gamma(L_bchw)
        if gamma is not None:
            g = torch.full_like(g, float(gamma))
        elif exposure is not None:
            g = self.tone.apply_exposure(g, float(exposure), self.illum_ref)
        return g.reshape(-1)

    def tone_map(self, R: Tensor, L: Tensor, gamma: Tensor) -> Tuple[Tensor, Tensor]:
        """(S_enh, L_enh) from R̂ [..., 3], the rendered L̂ [..., 3] and g ([1] or [3], broadcast over the last
        axis), in the model's tone form (``model.enhancement.tone``: :meth:`retinexgs.model.tones.Tone.map`)."""
        return self.tone.map(R, L, self.illum_ref, gamma, self.enhancement.eps, self.shoulder)

    def tone_linear(self, R: Tensor, L: Tensor, gamma: Tensor) -> Optional[Tensor]:
        """The enhanced linear light before the highlight shoulder and the sRGB curve of :meth:`tone_map`'s image,
        or None for a tone without a linear form, whose light is lin(S_enh) (:meth:`retinexgs.model.tones.Tone.linear`)."""
        return self.tone.linear(R, L, self.illum_ref, gamma)

    def predict_gamma(self, L_bchw: Tensor) -> Tensor:
        """The EnhancementNet's gamma for a normalised L̂/L_ref [1,3,H,W]: one per image (the paper's single g),
        repeated per channel as [1,C,1,1]. The net keeps its C outputs and their mean is the g, so that its
        parameters and the renderers' per-channel gamma input stay as every run has them."""
        g = self.enhancement(L_bchw)
        return g.mean(dim=1, keepdim=True).expand_as(g)

    def channels(self, center: Tensor, active_degree: int) -> Tensor:
        """The per-Gaussian channels a render of this model rasterizes from ``center`` (:func:`gaussian_channels`):
        [N,6] R̂ and L̂ values, or [N,3] colours for the plain-3DGS baselines."""
        return gaussian_channels(self.gaussians.means, self.gaussians.sh_dc, self.gaussians.sh_rest, center,
                                 self.channel_degree(active_degree), self.illumination if self.decomposed else None)

    def channel_degree(self, active_degree: int) -> int:
        """The SH degree evaluated at the trainer's ``active_degree`` (at most the model's)."""
        return min(active_degree, self.gaussians.sh_degree)

    def render(self, camera: Camera, active_degree: int, exposure: Optional[float] = None,
               gamma: Optional[float] = None, validate: bool = True, enhance: bool = True,
               center: Optional[Tensor] = None, colors: Optional[Tensor] = None, depth: bool = False,
               near: bool = True, pairs: Optional[PairBudget] = None, packed: bool = False) -> Dict[str, Tensor]:
        """Render one view. Returns ``out`` (RenderOutput) and [H,W,3] maps: ``rgb`` (the model's output
        image: S_enh, or the plain render for baselines), and for RetinexGS ``R``, ``L``, ``S_rec``, ``gamma``.

        ``exposure`` brightens (< 1) or darkens (> 1) the predicted exposure; ``gamma`` replaces the gamma.
        ``validate=False`` skips the renderer's input checks (one host sync), for loops that check their
        parameters themselves. ``enhance=False`` skips the EnhancementNet (no ``rgb``, ``L_enh``, ``gamma``):
        training needs only R̂ and L̂ until the enhancement losses start. ``center``: the camera centre already
        on the device (the trainer caches it per view; otherwise it is computed and copied every call).
        ``colors``: the per-Gaussian channels already evaluated (:func:`gaussian_channels`; the trainer's
        CUDA graph of them), else they are evaluated here. ``depth``: ``out`` also holds the alpha-weighted depth.
        ``near``: draw with the scene's near plane (:meth:`camera_for`); False draws as the camera says (training,
        unless ``model.near_in_training``). ``pairs``: bin without a host sync, the pair buffer sized by this
        :class:`PairBudget` (the trainer's; needs ``validate=False``). ``packed``: ``out.packed`` holds the channels,
        depth and alpha as one tensor (the captured loss's input, :func:`rasterize_gaussians`).
        """
        g = self.gaussians
        if near:
            camera = self.camera_for(camera)
        if colors is None:
            center = (camera.center if center is None else center).to(g.means)
            colors = self.channels(center, active_degree)
        out = rasterize_gaussians(g.means, g.quats, g.scales, g.opacities, colors, camera, validate=validate,
                                  render_depth=depth, background=self.background if self.has_background else None,
                                  pairs=pairs, packed=packed)
        if not self.decomposed:
            return {"out": out, "rgb": out.image}
        R, L = out.image[..., :3], out.image[..., 3:6]
        maps = {"out": out, "R": R, "L": L, "S_rec": R * L}
        return {**maps, **self.enhance(R, L, exposure, gamma)} if enhance else maps
