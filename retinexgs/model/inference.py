"""Inference renders of a trained scene with as few kernel launches as possible (``retinexgs render``, the viewer,
``python -m retinexgs.bench fps``).

:class:`InferenceRenderer` is built once from a trained :class:`~retinexgs.model.RetinexGSModel` and renders
frames equal to ``model.render(camera, degree, exposure, gamma)`` (same kernels, same maths), minus the
per-frame overhead of the training path:

- one fused kernel per frame (``retinexgs._C.gaussian_colors``, csrc/include/rgs/gaussian_colors.h) gives
  every Gaussian its SH reflectance and its illumination-MLP value, instead of ~40 small torch ops;
- projection, binning and compositing call the kernels directly (no autograd Functions, no per-frame
  validation); scales and opacities are activated once, the MLP weights packed once;
- on CUDA the enhancement (EnhancementNet + R̂·(L̂/L_ref)^g) is one CUDA graph per resolution (captured on
  the second frame of that size, the last few kept), with exposure and gamma in device tensors so one graph
  serves every setting;
- a white balance (``render --white-balance``, the viewer; issue 53) enters tone ``exposure``'s one kernel as a
  3×3 matrix on the linear light (:meth:`InferenceRenderer.render`'s ``balance``), in the same graph, rather than
  as a re-encoding of the frame in torch afterwards.

The renderer snapshots what it derives from the model (activated scales/opacities, packed weights). A model that
changes while frames render (a live trainer's viewer) needs ``live=True``: each frame then checks the parameters'
storage and version counters (tens of microseconds) and repacks what changed; otherwise call :meth:`refresh`
after changing the model (replaced Gaussian parameters, e.g. after densification, are noticed either way). Configurations the fused kernel
does not cover (illumination layers wider than ``retinexgs._C.max_illum_width``) use the torch colours.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import List, Optional, Sequence, Set, Tuple

import torch
from torch import Tensor, nn

from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.illumination import IlluminationField, encoded_dim
from retinexgs.model.tones.exposure import log_lin_ref
from retinexgs.render import cuda_graphs
from retinexgs.render._backend import kernels
from retinexgs.render.camera import Camera

__all__ = ["InferenceRenderer", "FrameMaps", "illumination_shape", "fused_colors_unsupported", "pack_illumination",
           "fused_gaussian_colors", "camera_center", "balanced_gain"]

MAX_GRAPHS = 4  # enhancement graphs kept (one per resolution; the viewer's scale slider makes new ones)


def illumination_shape(field: IlluminationField) -> Tuple[int, int, int, int, int]:
    """(pos_freqs, dir_freqs, hidden, depth, dir_hidden) of an illumination field, read from its layers."""
    trunk = [m for m in field.trunk if isinstance(m, nn.Linear)]
    head = [m for m in field.head if isinstance(m, nn.Linear)]
    return field.pos_freqs, field.dir_freqs, trunk[0].out_features, len(trunk), head[0].out_features


def fused_colors_unsupported(field: Optional[IlluminationField]) -> Optional[str]:
    """Why the fused colour kernel cannot evaluate ``field`` (None when it can)."""
    if field is None:
        return None
    pos_freqs, dir_freqs, hidden, depth, dir_hidden = illumination_shape(field)
    trunk = [m for m in field.trunk if isinstance(m, nn.Linear)]
    head = [m for m in field.head if isinstance(m, nn.Linear)]
    widest, most_freqs = int(kernels().max_illum_width), int(kernels().max_illum_freqs)
    if len(head) != 2 or head[1].out_features != 3 or trunk[0].in_features != encoded_dim(3, pos_freqs) \
            or head[0].in_features != hidden + encoded_dim(3, dir_freqs) \
            or any(m.in_features != hidden or m.out_features != hidden for m in trunk[1:]):
        return "the illumination field's layers are not the trunk/head MLP the kernel implements"
    if max(hidden, dir_hidden) > widest:
        return f"illumination widths hidden={hidden}, dir_hidden={dir_hidden} exceed the kernel's {widest}"
    if max(pos_freqs, dir_freqs) > most_freqs or depth > 64:
        return f"illumination pos_freqs={pos_freqs}, dir_freqs={dir_freqs}, depth={depth} exceed the kernel's limits"
    return None


def pack_illumination(field: IlluminationField) -> Tensor:
    """The field's MLP weights as the fused kernel's flat buffer (on the field's device and dtype)."""
    why = fused_colors_unsupported(field)
    if why is not None:
        raise ValueError(f"the fused colour kernel cannot evaluate this field: {why}")
    trunk = [m for m in field.trunk if isinstance(m, nn.Linear)]
    head = [m for m in field.head if isinstance(m, nn.Linear)]
    layers = trunk + head
    weights = [m.weight for m in trunk] + [field.head_weight(), head[1].weight]
    with torch.no_grad():
        return kernels().pack_illum_weights(weights, [m.bias for m in layers],
                                            *illumination_shape(field))


def camera_center(camera: Camera) -> List[float]:
    """The camera centre -Rᵀt in world space as three floats (plain Python: no tensor ops per frame)."""
    m = camera.kernel_args[0]
    t = (m[3], m[7], m[11])
    return [-(m[j] * t[0] + m[4 + j] * t[1] + m[8 + j] * t[2]) for j in range(3)]


def fused_gaussian_colors(gaussians: GaussianModel, center: Sequence[float], degree: int,
                          field: Optional[IlluminationField] = None, weights: Optional[Tensor] = None) -> Tensor:
    """[N,3] reflectance (``GaussianModel.colors``) or, with ``field``, [N,6] reflectance + illumination
    (``IlluminationField`` at the view directions) from one fused kernel; ``weights``: ``pack_illumination(field)``
    when already packed. ``degree`` is capped at the model's SH degree, as in ``colors``."""
    degree = min(int(degree), gaussians.sh_degree)
    if field is None:
        return kernels().gaussian_colors(degree, gaussians.means, gaussians.sh_dc, gaussians.sh_rest,
                                         [float(c) for c in center])
    if weights is None:
        weights = pack_illumination(field)
    return kernels().gaussian_colors(degree, gaussians.means, gaussians.sh_dc, gaussians.sh_rest,
                                     [float(c) for c in center], list(illumination_shape(field)), field.bound,
                                     weights.to(gaussians.means.dtype))


class FrameMaps(dict):
    """The maps of one frame: ``rgb``, and for RetinexGS ``R``, ``L``, ``gamma``; ``S_rec`` (R̂·L̂) is computed
    on first access (``maps["S_rec"]``), so frames that only show ``rgb`` do not pay for it."""

    def __missing__(self, key: str) -> Tensor:
        if key == "S_rec" and "R" in self and "L" in self:
            value = self["R"] * self["L"]
            self[key] = value
            return value
        raise KeyError(key)


def balanced_gain(balance: Tensor, gain: Tensor) -> Tensor:
    """The exposure tone kernel's 9-entry gain of a white balance W [3,3] and the exposure gain k ([1] or [3]):
    W·diag(k), row-major, so that the kernel's one pass gives shoulder(W·(k·lin(R̂∘L̂))) then the sRGB curve."""
    return (balance * gain.reshape(-1).expand(3)[None, :]).reshape(9)


class _EnhanceGraph:
    """The enhancement of one resolution captured as a CUDA graph: static input [H,W,6], exposure / fixed gamma
    in device tensors, output rgb [H,W,3] and gamma [C] in one buffer (copied out per frame)."""

    def __init__(self, model, height: int, width: int, like: Tensor, balanced: bool = False) -> None:
        self.model = model
        self.balanced = balanced  # a graph of its own: the unbalanced frame stays the one kernel call it was
        self.balance = torch.eye(3, dtype=like.dtype, device=like.device)
        self.balance_values: Optional[Tuple[float, ...]] = None
        self.image = torch.zeros(height, width, 6, dtype=like.dtype, device=like.device)
        self.exposure = torch.ones((), dtype=like.dtype, device=like.device)
        self.fixed = torch.ones((), dtype=like.dtype, device=like.device)
        self.use_fixed = torch.zeros((), dtype=torch.bool, device=like.device)
        self.settings: Tuple = (None, None)
        self.size = height * width * 3
        # A constant of the model (a change drops the graph): computed once, not as scalar kernels every frame.
        self.log_ref = log_lin_ref(model.illum_ref, self.image)
        side = torch.cuda.Stream(device=like.device)
        side.wait_stream(torch.cuda.current_stream(like.device))
        with torch.cuda.stream(side):
            for _ in range(2):  # warm-up outside the graph (cuDNN picks its algorithms here)
                self._body()
        torch.cuda.current_stream(like.device).wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        # thread_local: the viewer captures from its server thread while the main thread may use CUDA.
        with cuda_graphs.capture(self.graph, capture_error_mode="thread_local"):
            self.out = self._body()

    def _body(self) -> Tensor:
        R, L = self.image[..., :3], self.image[..., 3:6]
        L_bchw = self.model.normalized_illumination(L).permute(2, 0, 1).unsqueeze(0)
        g = self.model.predict_gamma(L_bchw)
        # RetinexGSModel.enhance: gamma replaces g, else exposure adjusts it (exposure 1, when unset: g exactly).
        tone = self.model.tone
        exposed = tone.apply_exposure(g, self.exposure, self.model.illum_ref, self.log_ref)
        g = torch.where(self.use_fixed, self.fixed, torch.where(self.exposure == 1.0, g, exposed))
        if tone.fusable():
            # One kernel for the tone (exposure's srgb(s(k·lin(R̂∘L̂))), csrc: exposure_tone): in torch the two
            # sRGB curves are ~20 elementwise kernels over the frame, and L_enh, which the frame does not show, as
            # many again.
            gain = tone.fused_gain(self.model.illum_ref, g.reshape(-1), self.log_ref)
            if self.balanced:
                gain = balanced_gain(self.balance, gain)
            rgb = tone.fused(self.image, gain, self.model.shoulder)
        else:  # a tone without a fused kernel (the gamma tones)
            rgb, _ = self.model.tone_map(R, L, g.reshape(-1))
        return torch.cat([rgb.reshape(-1), g.reshape(-1)])

    def run(self, image: Tensor, exposure: Optional[float], gamma: Optional[float],
            balance: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        """(rgb [H,W,3], gamma [C]) of a rasterized [H,W,6] image; both are fresh tensors. ``balance``: the 3×3
        white balance of a balanced graph."""
        if self.settings != (exposure, gamma):  # fill_ is a launch each: only when the GUI changes them
            self.use_fixed.fill_(gamma is not None)
            self.fixed.fill_(1.0 if gamma is None else float(gamma))
            self.exposure.fill_(1.0 if exposure is None else float(exposure))
            self.settings = (exposure, gamma)
        if self.balanced:
            values = tuple(balance.reshape(-1).tolist())  # the caller's copy (CPU in render and the viewer)
            if values != self.balance_values:  # a copy only when the balance changes
                self.balance.copy_(balance.reshape(3, 3))
                self.balance_values = values
        self.image.copy_(image)
        self.graph.replay()
        out = self.out.clone()
        h, w = self.image.shape[:2]
        return out[:self.size].view(h, w, 3), out[self.size:]


class InferenceRenderer:
    """Renders frames of a trained model (see the module docstring).

    Args:
        model: a :class:`~retinexgs.model.RetinexGSModel` (RetinexGS or a plain-3DGS baseline).
        degree: the active SH degree (capped at the model's).
        fused: use the fused colour kernel when it supports the model (False: the torch colours). The default,
            None, uses it on CUDA and the torch colours on the CPU, where BLAS evaluates the MLP faster than the
            kernel's one-Gaussian-per-iteration loop (the kernel is the GPU's; its CPU twin is the reference).
        graphs: capture the enhancement in CUDA graphs on CUDA (False: eager).
        live: the model changes between frames (see the module docstring); checked every frame.
    """

    def __init__(self, model, degree: int, fused: Optional[bool] = None, graphs: bool = True,
                 live: bool = False) -> None:
        self.model = model
        self.degree = int(degree)
        self.decomposed = bool(model.decomposed)
        field = model.illumination if self.decomposed else None
        on_cpu_default = fused is None and not model.gaussians.means.is_cuda
        if on_cpu_default:
            self.fallback_reason: Optional[str] = "the CPU default (BLAS is faster there)"
        else:
            self.fallback_reason = fused_colors_unsupported(field) if fused is not False else "disabled"
        self.fused = self.fallback_reason is None
        self.use_graphs = bool(graphs)
        self.live = bool(live)
        self.overlap_colors = True  # CUDA: the colour kernel on a side stream (False: after the binning)
        # Tile culling (pairs only where a Gaussian reaches alpha >= 1/255) changes no pixel, only the work split:
        # fewer pairs to sort and composite against a pair count that tests every tile twice. None: off on CUDA,
        # where on the trained fox-dark (83k Gaussians, H100) it costs 0.15-0.2 ms a frame more than it saves;
        # on on the CPU, where compositing dominates and it gained a few %
        # (experiments/notes/2026-11-22-raster-vs-gsplat.md).
        self.cull_tiles: Optional[bool] = None
        self._side: Optional["torch.cuda.Stream"] = None  # created on the first CUDA frame
        self._graphs: "OrderedDict[Tuple, _EnhanceGraph]" = OrderedDict()
        self._seen: Set[Tuple] = set()  # resolutions rendered once (captured on their second frame)
        self._stamp: Tuple = ()
        self._refresh()

    # ---- model state ---------------------------------------------------------------------------------------
    def _current_stamp(self) -> Tuple:
        # The networks' parameter objects are listed once per refresh; the Gaussians' are read each time, as
        # densification replaces them.
        g = self.model.gaussians
        return tuple((t.data_ptr(), t._version) for t in [g.log_scales, g.opacity_logits] + self._net_tensors)

    def refresh(self) -> None:
        """Recompute what is derived from the model (activations, packed weights) and drop the graphs."""
        self._refresh()

    def _refresh(self) -> None:
        g = self.model.gaussians
        self._net_tensors: List[Tensor] = []
        if self.decomposed:
            self._net_tensors = list(self.model.illumination.parameters()) + \
                list(self.model.enhancement.parameters()) + [self.model.illum_ref]
        self._sources = (g.log_scales, g.opacity_logits)
        with torch.no_grad():
            self.scales = torch.exp(g.log_scales).contiguous()
            self.opacities = torch.sigmoid(g.opacity_logits).contiguous()
            self.weights = pack_illumination(self.model.illumination) if self.decomposed and self.fused else None
        if self.decomposed:
            self.illum_shape = list(illumination_shape(self.model.illumination))
            self.bound = float(self.model.illumination.bound)
        self._graphs.clear()
        self._stamp = self._current_stamp()

    def refresh_if_changed(self) -> None:
        """Refresh when the model changed: any parameter (in place or replaced) when ``live``, else only replaced
        Gaussian parameters (two identity checks)."""
        g = self.model.gaussians
        if self.live:
            if self._current_stamp() != self._stamp:
                self._refresh()
        elif g.log_scales is not self._sources[0] or g.opacity_logits is not self._sources[1]:
            self._refresh()

    # ---- one frame -----------------------------------------------------------------------------------------
    def colors(self, camera: Camera) -> Tensor:
        """[N,6] (RetinexGS) or [N,3] (baselines) channels the rasterizer composites for ``camera``."""
        g = self.model.gaussians
        degree = min(self.degree, g.sh_degree)
        center = camera_center(camera)
        if self.fused:
            if self.decomposed:
                return kernels().gaussian_colors(degree, g.means, g.sh_dc, g.sh_rest, center, self.illum_shape,
                                                 self.bound, self.weights)
            return kernels().gaussian_colors(degree, g.means, g.sh_dc, g.sh_rest, center)
        return self.model.channels(torch.tensor(center, dtype=torch.float64).to(g.means), degree)

    def rasterize(self, camera: Camera, colors: Optional[Tensor] = None) -> Tensor:
        """[H,W,C] composited ``colors`` (the kernels of ``rasterize_gaussians``, without autograd or checks);
        ``colors`` None: this frame's :meth:`colors`. On CUDA they run on a side stream beside the projection and
        binning (they need neither; each fills only part of the GPU at scenes of ~100k Gaussians), and the
        binning's host sync waits for the main stream only; elsewhere they are launched after the binning."""
        K = kernels()
        g = self.model.gaussians
        camera = self.model.camera_for(camera)  # model.near_fraction's near plane, as model.render draws it
        ready = None
        if colors is None and g.means.is_cuda and self.overlap_colors:
            main = torch.cuda.current_stream(g.means.device)
            side = self._side_stream(g.means.device)
            side.wait_stream(main)  # the Gaussians as the main stream left them
            with torch.cuda.stream(side):
                colors = self.colors(camera)
            ready = torch.cuda.Event()
            ready.record(side)
        means2d, depths, conics, radii, _ = K.project_forward(g.means, g.quats, self.scales, self.opacities,
                                                              *camera.kernel_args)
        # With cull_tiles, pairs only where each Gaussian can reach alpha >= 1/255 (same pixels either way).
        on = (not g.means.is_cuda) if self.cull_tiles is None else self.cull_tiles
        cull = (conics, self.opacities) if on else (None, None)
        gauss_ids, tile_ranges = K.bin_gaussians(means2d, radii, depths, camera.width, camera.height, *cull)
        if ready is not None:
            main.wait_event(ready)
            colors.record_stream(main)  # allocated on the side stream, freed after the main stream's use
        elif colors is None:
            colors = self.colors(camera)
        # model.background: what uncovered pixels show (model.render's compositing), closed inside the kernel
        background = self.model.background.to(colors) if self.model.has_background else None
        return K.rasterize_forward(means2d, conics, colors, self.opacities, gauss_ids, tile_ranges, camera.width,
                                   camera.height, background)[0]

    def _side_stream(self, device: torch.device) -> "torch.cuda.Stream":
        stream = self._side
        if stream is None or stream.device != device:
            stream = self._side = torch.cuda.Stream(device=device)
        return stream

    def can_balance(self) -> bool:
        """Whether :meth:`render` applies a white balance itself: RetinexGS with a tone of one fused kernel (tone
        ``exposure``, the default). Elsewhere the caller balances the frame's light in torch."""
        return self.decomposed and self.model.tone.fusable()

    def render(self, camera: Camera, exposure: Optional[float] = None, gamma: Optional[float] = None,
               degree: Optional[int] = None, balance: Optional[Tensor] = None) -> FrameMaps:
        """The frame of ``camera``: ``rgb`` [H,W,3] equal to ``model.render(camera, degree, exposure, gamma)["rgb"]``
        and, for RetinexGS, ``R``, ``L``, ``S_rec`` [H,W,3] and ``gamma`` [C]. ``exposure`` adjusts the predicted
        gamma, ``gamma`` replaces it (RetinexGS only; baselines ignore both). ``degree`` overrides the SH degree
        of this and later frames (a live trainer raises it). ``balance``: a white balance, gains [3] or a 3×3 matrix
        on the linear light (:mod:`retinexgs.model.white_balance`), applied before the highlight
        shoulder and the sRGB curve, as ``render --white-balance`` defines it; only where :meth:`can_balance`
        (else refused: the caller balances). None: as trained."""
        if balance is not None and not self.can_balance():
            raise ValueError("this model's tone has no fused white balance (can_balance() is False)")
        if degree is not None:
            self.degree = int(degree)
        self.refresh_if_changed()
        with torch.no_grad():
            image = self.rasterize(camera)
            if not self.decomposed:
                return FrameMaps(rgb=image)
            R, L = image[..., :3], image[..., 3:6]
            balanced = balance is not None
            if balanced:  # kept where the caller has it (the CPU, from numpy): no device-to-host read per frame
                balance = torch.as_tensor(balance)
                balance = torch.diag(balance) if balance.dim() == 1 else balance.reshape(3, 3)
            graph = (self._graph(camera.height, camera.width, image, balanced)
                     if self.use_graphs and image.is_cuda else None)
            if graph is not None:
                rgb, g = graph.run(image, exposure, gamma, balance)
            elif balanced:
                g = self.model.enhance_gamma(L, exposure, gamma)
                gain = balanced_gain(balance.to(image), self.model.tone.fused_gain(self.model.illum_ref, g))
                rgb = self.model.tone.fused(image, gain, self.model.shoulder)
            else:
                enh = self.model.enhance(R, L, exposure, gamma)
                rgb, g = enh["rgb"], enh["gamma"]
            return FrameMaps(rgb=rgb, R=R, L=L, gamma=g)

    def _graph(self, height: int, width: int, like: Tensor, balanced: bool = False) -> Optional[_EnhanceGraph]:
        """The enhancement graph of this resolution (and balanced or not); None (render eagerly) the first time a
        resolution is seen, so frames of ever-changing sizes do not pay a capture each."""
        key = (height, width, like.dtype, like.device, balanced)
        graph = self._graphs.get(key)
        if graph is None:
            if key not in self._seen:
                if len(self._seen) > 64:
                    self._seen.clear()
                self._seen.add(key)
                return None
            graph = _EnhanceGraph(self.model, height, width, like, balanced)
            self._graphs[key] = graph
            while len(self._graphs) > MAX_GRAPHS:
                self._graphs.popitem(last=False)
        else:
            self._graphs.move_to_end(key)
        return graph

