"""Bake a trained RetinexGS scene into plain 3DGS Gaussians (SH colours only) for standard viewers.

The enhanced image of RetinexGS is a tone map of R̂ and L̂ (:mod:`retinexgs.model.tone`; e.g. clip(R̂ ∘ E(L̂), 0, 1)
with E(L) = max(min(L / L_ref, 1), eps)^g for tone ``illumination``, srgb(k · lin(R̂ ∘ L̂)) for the default
``exposure``): R̂ comes from the Gaussians' SH (albedo), L̂ from an MLP evaluated per Gaussian and view
direction, L_ref is a scene-wide illumination reference and g comes from the EnhancementNet. The PLY's comment
states the run's formula and numbers (:func:`baked_colour_text`). A standard viewer can only evaluate SH, so
for every Gaussian the enhanced colour

    c(d) = tone(R(d), L(x, d)), clipped to [0, 1]

is evaluated from ``directions`` unit directions d (a Fibonacci sphere; d points from the camera to the
Gaussian, the convention of both the SH and the illumination field) and SH coefficients of the model's
degree D are fitted to c(d) − 0.5 by least squares (colour = max(SH(d) + 0.5, 0) in 3DGS). E is the model's
own tone map (``RetinexGSModel.tone_map``), so the bake follows the render. g is the
mean of the gammas the EnhancementNet predicts over the training views (per channel when the model predicts
per channel), optionally adjusted by an exposure factor (:func:`retinexgs.model.tone.apply_exposure`) or
replaced by a fixed gamma.

A white balance (``export --white-balance``, :mod:`retinexgs.model.white_balance`) is baked the way the render
applies it: in the enhanced colour's linear light before the highlight shoulder and the sRGB curve (tone
``exposure``: W·k·lin(R̂∘L̂); the gamma tones: W·lin(S_enh)), through the same functions
(:func:`retinexgs.model.tone.white_balance`); the fit then sees the balanced colour. As trained (no balance, or
exactly gains 1, 1, 1) the baked SH are bit for bit those of a bake without it.

What the bake cannot reproduce exactly (also said in docs/usage.md, "Render and export"): the model composites R̂ and L̂
*before* raising L̂ to g and multiplying, the bake multiplies per Gaussian and lets the viewer composite.
The two agree where one opaque Gaussian dominates a pixel; where several semi-transparent Gaussians mix, or
coverage is partial (alpha < 1), they differ: a pixel of alpha a shows a·R·E(L) in the viewer instead of
the model's a·R·E(a·L), i.e. the PLY is brighter there. On the tiny test run, whose coverage is like a
trained scene's, the PLY renders at 36–38 dB PSNR against the full model (tests/test_export.py); on one
with half-transparent coverage, about 27 dB. The per-view gamma becomes one gamma for all views, and a
degree-D SH only approximates the illumination's view dependence.

The world mapping itself is exact up to float32 rounding: the scene normalisation is a translation and a
uniform scale, which move and resize the Gaussians but change no direction, so the SH colours need no
change. What stays in the normalised frame is only implicit: the illumination field was evaluated at the
normalised positions before baking, and the rasterizer's near plane (0.01) is in normalised units.
"""
from __future__ import annotations

import math
from typing import Callable, Dict, Iterable, Optional

import torch
from torch import Tensor

from retinexgs.data.scene import Normalization
from retinexgs.model.gaussians import PARAM_NAMES
from retinexgs.model.inference import InferenceRenderer
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.model.tone import highlight_shoulder, linear_to_srgb, srgb_to_linear, white_balance
from retinexgs.model.white_balance import WhiteBalance, describe_balance
from retinexgs.render import Camera, spherical_harmonics


def fibonacci_sphere(n: int, dtype: torch.dtype = torch.float64) -> Tensor:
    """``n`` nearly uniform unit directions [n,3] (golden-angle spiral)."""
    i = torch.arange(n, dtype=dtype) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """[n, (degree+1)²] SH basis values at ``dirs`` [n,3], from the renderer's own SH (so the fit uses the
    exact basis the rasterizer and the viewers evaluate)."""
    k = (degree + 1) ** 2
    eye = torch.eye(k, dtype=dirs.dtype, device=dirs.device).expand(dirs.shape[0], k, k).contiguous()
    return spherical_harmonics(degree, dirs, eye)


def mean_gamma(model: RetinexGSModel, cameras: Iterable[Camera], degree: int) -> Tensor:
    """The mean gamma [3] the EnhancementNet predicts over ``cameras`` (one value repeated unless per channel)."""
    gammas = []
    renderer = InferenceRenderer(model, degree)  # the render command's frames: same gamma as model.render
    with torch.no_grad():
        for cam in cameras:
            gammas.append(renderer.render(cam)["gamma"].reshape(-1, 3).mean(0).double().cpu())
    if not gammas:
        raise ValueError("mean_gamma needs at least one camera")
    return torch.stack(gammas).mean(0)


def enhanced_colour(model: RetinexGSModel, R: Tensor, L: Tensor, gamma: Tensor,
                    balance: Optional[Tensor] = None) -> Tensor:
    """The enhanced colour (sRGB, [0, 1]) of R̂ [..., 3] and L̂ [..., 3] per Gaussian and direction under gamma g,
    with the white balance ``balance`` (gains [3] or a 3×3 matrix; None: as trained) applied in linear light
    before the highlight shoulder and the sRGB curve, as ``render --white-balance`` applies it.

    Without a balance: ``model.tone_map``'s colour, bit for bit."""
    tone = model.tone
    light = tone.linear(R, L, model.illum_ref, gamma)
    if light is not None:  # a tone with a linear form (exposure): the balance acts on it
        return linear_to_srgb(highlight_shoulder(white_balance(light, balance), tone.knee(model.shoulder)))
    colour = tone.map(R, L, model.illum_ref, gamma, model.enhancement.eps, model.shoulder)[0]
    if balance is None:
        return colour
    return linear_to_srgb(white_balance(srgb_to_linear(colour), balance))  # the gamma tones clip before: [0, 1]


def bake_enhanced_sh(model: RetinexGSModel, active_degree: int, gamma: Tensor, directions: int = 64,
                     chunk: int = 4096, progress: Optional[Callable[[int], None]] = None,
                     balance: Optional[Tensor] = None) -> Dict[str, Tensor]:
    """SH coefficients (``sh_dc`` [N,1,3], ``sh_rest`` [N,K-1,3], K = (model degree + 1)²) that least-squares fit
    each Gaussian's enhanced colour clip(R(d)·E(L(x,d)), 0, 1) (module docstring) over ``directions`` Fibonacci
    directions.

    R is evaluated at ``active_degree`` (what the model renders with); the fit uses the model's full degree,
    which the PLY stores. ``gamma`` is a scalar or [3]. ``progress(n)`` is called after each chunk of n.
    ``balance``: a white balance (gains [3] or a 3×3 matrix; :func:`enhanced_colour`), None: as trained.
    """
    g = model.gaussians
    degree = g.sh_degree
    k = (degree + 1) ** 2
    if directions < k:
        raise ValueError(f"--directions must be at least {k} to fit degree-{degree} SH, got {directions}")
    device = g.means.device
    dirs = fibonacci_sphere(directions).to(device)
    fit = torch.linalg.pinv(sh_basis(degree, dirs))                      # [K, n_dirs], float64
    act = min(active_degree, degree)
    basis_act = sh_basis(act, dirs).float()                              # [n_dirs, K_act]
    dirs32 = dirs.float()
    gamma = torch.as_tensor(gamma, dtype=torch.float32, device=device).reshape(-1)
    if balance is not None:
        balance = torch.as_tensor(balance, dtype=torch.float32, device=device)
    coeffs = torch.cat([g.sh_dc, g.sh_rest], dim=1).detach()[:, :(act + 1) ** 2]
    out = torch.empty(len(g), k, 3, dtype=torch.float32, device=device)
    with torch.no_grad():
        for s in range(0, len(g), chunk):
            means = g.means[s:s + chunk]
            n = means.shape[0]
            R = (torch.einsum("dk,nkc->ndc", basis_act, coeffs[s:s + chunk]) + 0.5).clamp_min(0.0)
            # The same field and direction convention as RetinexGSModel.render: d from the camera to the Gaussian.
            L = model.illumination(means.repeat_interleave(directions, 0), dirs32.repeat(n, 1)).reshape(n, -1, 3)
            # The model's own tone functions, so the bake follows the enhanced render.
            target = enhanced_colour(model, R, L.float(), gamma, balance)
            out[s:s + n] = torch.einsum("kd,ndc->nkc", fit, (target - 0.5).double()).float()
            if progress is not None:
                progress(n)
    return {"sh_dc": out[:, :1].contiguous(), "sh_rest": out[:, 1:].contiguous()}


def baked_colour_text(model: RetinexGSModel, gamma: Tensor, directions: int, wb: Optional[WhiteBalance] = None,
                      balance=None) -> str:
    """The PLY comment saying what :func:`bake_enhanced_sh` baked: the formula of the model's tone form
    (``model.enhancement.tone``, :mod:`retinexgs.model.tone`) with its numbers (g; for tone ``exposure`` the gain k
    and the highlight knee), and with ``wb`` the
    white balance W in the formula and its numbers (:func:`retinexgs.model.white_balance.describe_balance`)."""
    g = torch.as_tensor(gamma, dtype=torch.float64).reshape(-1).cpu()
    text = model.tone.describe(g, model.illum_ref, model.shoulder, balance is not None)
    if wb is not None:  # beside the exposure's numbers: the form given and W's numbers (or none: as trained)
        text += f"; W = {describe_balance(wb, balance)}" if balance is not None else f"; {describe_balance(wb, None)}"
    return text + f", clipped to [0,1] and baked into SH by least squares over {directions} directions"


def reflectance_sh(model: RetinexGSModel, active_degree: int) -> Dict[str, Tensor]:
    """R̂'s SH as stored, with the bands above ``active_degree`` zeroed: the model renders without them, and a
    viewer would otherwise add whatever they hold."""
    g = model.gaussians
    rest = g.sh_rest.detach().clone()
    rest[:, (min(active_degree, g.sh_degree) + 1) ** 2 - 1:] = 0.0
    return {"sh_dc": g.sh_dc.detach().clone(), "sh_rest": rest}


def to_world(params: Dict[str, Tensor], norm: Normalization) -> Dict[str, Tensor]:
    """Gaussians from the normalised working frame to the input's world frame: centres through
    ``norm.to_world`` and standard deviations divided by ``norm.scale`` (log-scales shifted); rotations,
    opacities and SH are unchanged (a translation plus uniform scale changes no direction)."""
    out = dict(params)
    out["means"] = norm.to_world(params["means"].detach().double()).float()
    out["log_scales"] = (params["log_scales"].detach().double() - math.log(norm.scale)).float()
    return out


def to_normalized(params: Dict[str, Tensor], norm: Normalization) -> Dict[str, Tensor]:
    """The inverse of :func:`to_world` (e.g. to render an exported PLY in the run's frame)."""
    out = dict(params)
    out["means"] = norm.to_normalized(params["means"].detach().double()).float()
    out["log_scales"] = (params["log_scales"].detach().double() + math.log(norm.scale)).float()
    return out


def export_params(model: RetinexGSModel, norm: Normalization, sh: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """The model's Gaussians with the SH of ``sh``, mapped to the world frame, on the CPU (the PLY's content)."""
    g = model.gaussians
    params = {name: getattr(g, name).detach() for name in PARAM_NAMES}
    params.update(sh)
    return {name: t.cpu() for name, t in to_world(params, norm).items()}
