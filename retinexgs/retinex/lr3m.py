"""LR3M (Ren, Yang, Cheng, Liu, "LR3M: Robust Low-Light Enhancement via Low-Rank Regularized Retinex
Model", IEEE TIP 2020), reconstructed in torch from the public description.

Model:  S = R∘L + N,
        min_{R,L} ‖R∘L − S‖² + β‖∇L‖₁ + ω‖∇R − G‖² + (low-rank prior on groups of similar patches of R)

L sub-problem (solved once, LIME-style): ‖L − L̂‖² + β‖∇L‖₁ is relaxed to the weighted quadratic
(I + Σ_d D_dᵀ diag(a_d) D_d) l = l̂, a_d = β/(|∇_d L̂| + ε), L̂ = max-RGB (see ``illumination.py``).

R sub-problem, ADMM with the split R = R̂, multiplier Z, μ ← ρμ (μ0 = 1, ρ = 1.5):
    R̂ = (2ω DᵀD + μI)⁻¹ (2ω Dᵀ G + μR + Z)                 (solved exactly by FFT, Neumann boundaries)
    R̄ = (2 S∘L + μR̂ − Z) / (2L² + μ)                       (pixel-wise, fidelity + split)
    R  = LowRank(R̄)                                         (patch groups + weighted SVT, ``lowrank.py``)
    Z ← Z + μ(R − R̂)
G is the gradient-fidelity target  G = K∘∇Ŝ,  K = 1 + λ e^{−|∇Ŝ|/σ},  ∇Ŝ = 0 where |∇S| < ε.

Choices made where the public description is silent (also in docs/retinex.md):
- Illumination has ONE channel (the LR3M/LIME convention); R carries the colour.
- Exposure invariance: S and L are divided by the 99th percentile of L before the R sub-problem, so the
  published weights (set for normally exposed images) act the same on a photo 20× darker. R is unchanged
  by this (S/L is scale free) and L is returned in the scale of S, so R∘L ≈ S.
- G is built from Ŝ = S/L (the naive reflectance, clipped to [0,1]) rather than from the dark S; otherwise
  the gradient term would pull R towards the low contrast of the dark photo. The threshold ε is
  noise-adaptive: max(ε_published/255, k·√2·σ_S/L) — a gradient is kept only when it is k standard
  deviations above the gradient noise at that pixel (the noise of S/L grows where L is small) and when
  the 3×3 median of Ŝ has a gradient there too (``median_guide``; removes isolated-spike speckles).
- Noise σ_w: σ_S of the normalised S is estimated once by the Haar-MAD rule; the noise of R̄ at a pixel is
  taken as γ_s^k·σ_S/L at ADMM iteration k (γ_s = 0.65, the published value, as a geometric decay: R̄
  gets cleaner with each iteration); each group uses the mean over its reference patch.
- Block matching runs on the luma of R̂ (the edge-preserving smooth estimate; grey level = mean of RGB)
  at the first iteration and is reused
  (``rematch_every`` > 0 re-matches); candidates lie on a ``search_step`` grid within ±``search_radius``.
- R is clipped to [0,1] once at the end; L is floored at ``l_floor`` × its 99th percentile.
- ``delta`` (0.23) is listed by the public demo with no documented role; it is kept in the parameters
  (and in the cache key) for reference but not used.
- Memory: the R sub-problem's working set is about 1.4 KB per pixel on the CPU (every overlapping patch of R and
  its groups): 2.7 GiB for a 1080p photo, 15 GiB for a 12 MP one. Above ``tile_pixels`` it runs in tiles of at most
  that many pixels, each a core plus ``tile_margin`` px of context on every side, keeping each core; the
  illumination, the exposure scale q and the noise σ_S stay the whole photo's. The result differs from the whole
  photo's only through the context a core lacks (``tests/test_retinex.py``); photos up to 1920×1080 are not tiled
  at the default, nor larger ones whose working set fits ``tile_memory_share`` of the device's free memory (tiles
  are slower: a 12 MP photo took 5.5 s on tiles and 2.3 s whole on an H100, at 4.6 and 14.9 GiB).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any, ClassVar, Dict, Iterator, Optional, Tuple

import torch
import torch.nn.functional as F

from retinexgs.retinex.base import Decomposer
from retinexgs.retinex.illumination import (grad_x, grad_x_t, grad_y, grad_y_t, max_rgb, percentile_scale,
                                            refine_illumination)
from retinexgs.retinex.lowrank import block_match, estimate_noise_sigma, group_noise, lowrank_denoise


@dataclass(frozen=True)
class LR3MParams:
    """LR3M parameters. The first block are the published demo values; the rest are our choices."""

    beta: float = 0.015       # illumination smoothness β
    omega: float = 2.0        # weight ω of the gradient-fidelity term ‖∇R − G‖²
    lam: float = 2.5          # λ: gradient amplification in K = 1 + λ e^{−|∇Ŝ|/σ}
    sigma: float = 10.0       # σ of K, on the 0–255 scale
    eps: float = 1.0          # gradient threshold floor for ∇Ŝ, on the 0–255 scale
    gamma: float = 2.2        # display gamma for S' = R∘(L/max L)^{1/γ}
    delta: float = 0.23       # published, role undocumented; unused
    gamma_s: float = 0.65     # decay of the assumed noise level per ADMM iteration
    mu0: float = 1.0          # ADMM penalty start
    rho: float = 1.5          # ADMM penalty growth
    iterations: int = 3       # ADMM outer iterations (published ~5; 3 is faster and better here, see docs)
    patch: int = 7            # patch side (patches are patch×patch×3)
    stride: int = 6           # reference grid stride
    search_radius: int = 25   # block-matching window ±px
    search_step: int = 2      # candidate grid step inside the window (published: dense, 1)
    group_size: int = 32      # patches per group (published 40; 32 lets CUDA batch the 32x32 eighs: 14 s -> 0.06 s per image on an H100)
    c1: float = 2.9 * math.sqrt(2.0)  # SVT weight constant
    # --- not published: implementation choices
    illum_eps: float = 1e-3   # ε in a_d = β/(|∇L̂|+ε) on the normalised L̂
    weight_sigma: float = 2.0  # Gaussian σ (px) smoothing ∇L̂ before the weights (LIME strategy III)
    cg_tol: float = 1e-4      # relative residual for the PCG illumination solve
    cg_max_iter: int = 300
    grad_noise_k: float = 3.0  # keep ∇Ŝ only above k·(gradient noise std)
    l_floor: float = 0.02     # L >= l_floor × 99th percentile of L
    median_guide: bool = True  # keep ∇Ŝ only where a 3×3 median of S/L also has a gradient (no speckles)
    rematch_every: int = 0    # 0: block matching once; n: again every n iterations
    solver: str = "gram"      # "gram" (eigh of the n×n Gram matrix) or "svd" (torch.linalg.svd)
    tile_pixels: int = 1 << 21  # memory bound: larger photos solve R in tiles of at most this many pixels
    tile_margin: int = 96     # context px on each side of a tile's core (a multiple of ``stride``)
    # A photo above tile_pixels is still solved whole where its working set fits this share of the memory free on
    # its device (tiles cost 1.5x the time on the CPU, 2.5x on an H100); 0: always tiles above tile_pixels. 0.75
    # (0.5 until 2026-11-29): a 24 GB card (~23 GiB free) solves a 12 MP photo whole (15.6 GiB budgeted, 14.9
    # measured), 2.0 s instead of 5.5 on tiles on an H100, and a quarter of the free memory stays spare. An H200
    # capped at 24 GB wrote the 12 MP raw scene's 40 views in 109 s, as uncapped (tiles would add ~140 s):
    # experiments/notes/2026-11-29-12mp-and-seeds.md.
    tile_memory_share: float = 0.75

    # Added after caches existed: at these values they are left out of the cache key, so that a cache written
    # before them stays valid (the photos it holds were decomposed whole; tiles change R only near seams, by
    # less than float32 matters: 77.9 dB PSNR against the whole photo, so a cache may mix both; for the same reason
    # the share's default moved from 0.5 to 0.75 under the same key).
    KEY_OMIT_AT_DEFAULT: ClassVar[Dict[str, Any]] = {"tile_pixels": 1 << 21, "tile_margin": 96,
                                                     "tile_memory_share": 0.75}


def _neumann_solve(rhs: torch.Tensor, a: float, mu: float) -> torch.Tensor:
    """Solve (a·DᵀD + μI) x = rhs for [B,C,H,W] with Neumann forward differences D.

    The even (half-sample) mirror extension turns the Neumann Laplacian into a periodic one that the FFT
    diagonalises, with eigenvalues 4 sin²(πk/2N) per axis.
    """
    h, w = rhs.shape[-2:]
    ext = torch.cat([rhs, rhs.flip(-1)], dim=-1)
    ext = torch.cat([ext, ext.flip(-2)], dim=-2)
    fy = torch.arange(2 * h, device=rhs.device, dtype=rhs.dtype)
    fx = torch.arange(w + 1, device=rhs.device, dtype=rhs.dtype)
    lam_y = 4.0 * torch.sin(math.pi * fy / (2 * h)) ** 2
    lam_x = 4.0 * torch.sin(math.pi * fx / (2 * w)) ** 2
    denom = a * (lam_y.view(-1, 1) + lam_x.view(1, -1)) + mu
    x = torch.fft.irfft2(torch.fft.rfft2(ext) / denom, s=(2 * h, 2 * w))
    return x[..., :h, :w].contiguous()


def _median3(x: torch.Tensor) -> torch.Tensor:
    """3×3 median filter of [B,C,H,W] (replicate borders)."""
    b, c, h, w = x.shape
    cols = F.unfold(F.pad(x, (1, 1, 1, 1), mode="replicate").reshape(b * c, 1, h + 2, w + 2), 3)
    return cols.median(dim=1).values.view(b, c, h, w)


def _gradient_target(r0: torch.Tensor, sig_r0: torch.Tensor, p: LR3MParams) -> Tuple[torch.Tensor, torch.Tensor]:
    """G = (1 + λ e^{−|∇Ŝ|/σ}) ∘ ∇Ŝ with ∇Ŝ zeroed below the noise-adaptive threshold; returns (G_x, G_y).

    With ``median_guide`` a gradient is also dropped unless the 3×3 median of Ŝ has one there too: an
    isolated noise spike passes any threshold (and would be copied into R as a speckle) but has no
    gradient in the median image, while real edges keep their exact, unfiltered gradient.
    """
    floor = p.eps / 255.0
    sigma = p.sigma / 255.0
    med = _median3(r0) if p.median_guide else None
    out = []
    for grad, pair in ((grad_x, lambda m: 0.5 * (m[..., :, 1:] + m[..., :, :-1])),
                       (grad_y, lambda m: 0.5 * (m[..., 1:, :] + m[..., :-1, :]))):
        g = grad(r0)
        thresh = (p.grad_noise_k * math.sqrt(2.0) * pair(sig_r0)).clamp_min(floor)
        drop = g.abs() < thresh
        if med is not None:
            drop |= grad(med).abs() < 0.5 * thresh  # the median leaves ~half the noise
        g = torch.where(drop, torch.zeros_like(g), g)
        out.append((1.0 + p.lam * torch.exp(-g.abs() / sigma)) * g)
    return out[0], out[1]


class LR3M(Decomposer):
    """Low-rank regularised Retinex decomposition (the default method). See the module docstring."""

    name = "lr3m"
    Params = LR3MParams

    def _decompose_batch(self, s: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        p: LR3MParams = self.params
        if p.solver not in ("gram", "svd"):
            raise ValueError(f"LR3M solver must be 'gram' or 'svd', got {p.solver!r}")
        if min(s.shape[-2:]) < p.patch + 1:
            raise ValueError(f"image must be larger than the {p.patch}x{p.patch} patch, got {tuple(s.shape[-2:])}")
        tile_side(p)  # bad tile parameters are refused whatever the photo's size
        # --- illumination: max-RGB refined by the structure-aware SPD solve
        l = refine_illumination(max_rgb(s), p.beta, p.illum_eps, p.weight_sigma, p.cg_tol, p.cg_max_iter)
        q = percentile_scale(l)
        l = torch.maximum(l, p.l_floor * q)
        lt, st = l / q, s / q  # exposure-normalised (R unchanged)

        # --- reflectance: ADMM with gradient fidelity and the low-rank prior, on tiles above tile_pixels
        sig_s = estimate_noise_sigma(st).view(-1, 1, 1, 1)
        h, w = s.shape[-2:]
        if solve_whole(h * w, s.shape[0], s.device, p):
            return self._reflectance(st, lt, sig_s).clamp(0.0, 1.0), l
        r = torch.empty_like(st)
        for (y0, y1, x0, x1), (cy0, cy1, cx0, cx1) in tiles(h, w, p):
            part = self._reflectance(st[..., y0:y1, x0:x1], lt[..., y0:y1, x0:x1], sig_s)
            r[..., cy0:cy1, cx0:cx1] = part[..., cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0]
            del part
        return r.clamp(0.0, 1.0), l

    def _reflectance(self, st: torch.Tensor, lt: torch.Tensor, sig_s: torch.Tensor) -> torch.Tensor:
        """The R sub-problem on [B,3,h,w] exposure-normalised S and [B,1,h,w] L (σ_S [B,1,1,1] given: the
        whole photo's), unclipped."""
        p: LR3MParams = self.params
        r0 = (st / lt).clamp(0.0, 1.0)
        sig_r0 = (sig_s / lt).clamp(max=0.5)
        gx, gy = _gradient_target(r0, sig_r0, p)
        two_w = 2.0 * p.omega
        rhs_g = two_w * (grad_x_t(gx) + grad_y_t(gy))
        del gx, gy
        two_sl, two_l2 = 2.0 * st * lt, 2.0 * lt * lt

        r, z, mu = r0, torch.zeros_like(r0), p.mu0
        groups: list = [None] * st.shape[0]
        for k in range(p.iterations):
            r_hat = _neumann_solve(rhs_g + mu * r + z, two_w, mu)
            r_bar = (two_sl + mu * r_hat - z) / (two_l2 + mu)
            sig_map = (p.gamma_s ** k) * sig_r0
            rematch = k == 0 or (p.rematch_every > 0 and k % p.rematch_every == 0)
            r_new = torch.empty_like(r_bar)
            for b in range(st.shape[0]):
                if rematch:
                    # Match on the luma of R̂ (as BM3D matches on Y): 3× less data, no loss in our tests.
                    groups[b] = block_match(r_hat[b].mean(0, keepdim=True), p.patch, p.stride, p.search_radius, p.search_step,
                                            p.group_size)
                sig = group_noise(sig_map[b], p.patch, p.stride)
                r_new[b] = lowrank_denoise(r_bar[b], groups[b], sig, p.patch, p.c1, p.solver)
            r = r_new
            z = z + mu * (r - r_hat)
            mu *= p.rho
        return r


# The R sub-problem's working set per pixel of a photo solved whole: 1.36 KB/px measured on the CPU and 1.33 KB/px
# on an H100 (a 12 MP photo: 15.15 and 14.91 GiB, `bench lr3m --resize 3000x4000`), rounded up.
WHOLE_BYTES_PER_PIXEL = 1400


def free_memory_bytes(device: torch.device) -> Optional[int]:
    """Memory a decomposition on ``device`` may use now: on CUDA the driver's free memory plus what torch's
    allocator holds unused, within the process's memory fraction; on the CPU Linux's MemAvailable, shared among the
    ranks of this host (LOCAL_WORLD_SIZE under torchrun). None where it cannot be read."""
    if device.type == "cuda":
        free, total = torch.cuda.mem_get_info(device)
        allocated = torch.cuda.memory_allocated(device)
        usable = free + torch.cuda.memory_reserved(device) - allocated
        # a per-process cap (torch.cuda.set_per_process_memory_fraction: a smaller card's share) bounds it too
        capped = torch.cuda.get_per_process_memory_fraction(device) * total - allocated
        return int(max(min(usable, capped), 0))
    if device.type != "cpu":
        return None
    try:
        with open("/proc/meminfo") as f:
            kib = next(int(line.split()[1]) for line in f if line.startswith("MemAvailable:"))
    except (OSError, StopIteration, ValueError, IndexError):
        return None
    try:
        ranks = max(int(os.environ.get("LOCAL_WORLD_SIZE", "1")), 1)
    except ValueError:
        ranks = 1
    return kib * 1024 // ranks


def solve_whole(pixels: int, batch: int, device: torch.device, p: LR3MParams) -> bool:
    """Whether a batch of photos of ``pixels`` each solves R whole: up to ``tile_pixels``, or above it where the
    whole photos' working set (:data:`WHOLE_BYTES_PER_PIXEL`) fits ``tile_memory_share`` of the free memory
    (:func:`free_memory_bytes`; tiles where that is unknown)."""
    if pixels <= p.tile_pixels:
        return True
    if p.tile_memory_share <= 0:
        return False
    free = free_memory_bytes(torch.device(device))
    return free is not None and WHOLE_BYTES_PER_PIXEL * pixels * batch <= p.tile_memory_share * free


def tile_side(p: LR3MParams) -> int:
    """The side of a tile's core; a ValueError names bad tile parameters."""
    for name in ("tile_pixels", "tile_margin"):
        value = getattr(p, name)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"LR3M tiles: {name} must be an integer, got {value!r}")
    share = p.tile_memory_share
    if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0.0 <= share <= 1.0:
        raise ValueError(f"LR3M tiles: tile_memory_share must be a number in [0, 1], got {share!r}")
    m = p.tile_margin
    side = (math.isqrt(max(p.tile_pixels, 0)) - 2 * m) // p.stride * p.stride
    if m < 0 or m % p.stride or side < 4 * p.stride:
        raise ValueError(f"LR3M tiles: tile_margin={m} must be a non-negative multiple of stride={p.stride} and "
                         f"tile_pixels={p.tile_pixels} at least ({2 * m + 4 * p.stride})² (a core of 4 strides)")
    return side


def tiles(h: int, w: int, p: LR3MParams) -> Iterator[Tuple[Tuple[int, int, int, int], Tuple[int, int, int, int]]]:
    """The tiles of an h×w photo: ((y0, y1, x0, x1) of the tile, (y0, y1, x0, x1) of its core), cores covering
    the photo once. A tile is its core and ``tile_margin`` px on each side (clipped at the photo's edge; a thin
    last core without margin gets context to reach a patch) and has at most ``tile_pixels`` pixels. Cores are
    square, of a side that is a multiple of ``stride``, so every tile starts on the whole photo's reference grid;
    the last row and column of cores take what is left."""
    m, side = p.tile_margin, tile_side(p)
    for cy0 in range(0, h, side):
        for cx0 in range(0, w, side):
            cy1, cx1 = min(cy0 + side, h), min(cx0 + side, w)
            y1, x1 = min(cy1 + m, h), min(cx1 + m, w)
            yield (_start(cy0, y1, p), y1, _start(cx0, x1, p), x1), (cy0, cy1, cx0, cx1)


def _start(c0: int, end: int, p: LR3MParams) -> int:
    """A tile's first row (column): ``tile_margin`` before its core, earlier (on the stride grid) where the
    tile would be narrower than a patch and a pixel (a thin last core without margin)."""
    start = max(c0 - p.tile_margin, 0)
    if end - start < p.patch + 1:
        start = max((end - p.patch - 1) // p.stride * p.stride, 0)
    return start


def lr3m_decompose(image: torch.Tensor, params: Optional[LR3MParams] = None, **overrides) -> Tuple[torch.Tensor, torch.Tensor]:
    """Functional shortcut: ``LR3M(params, **overrides).decompose(image)``."""
    return LR3M(params, **overrides).decompose(image)
