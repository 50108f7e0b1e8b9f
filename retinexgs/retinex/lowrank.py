"""LR3M's low-rank prior: group similar patches, shrink each group's singular values, put them back.

Pipeline for one [3,H,W] image (every stage batched over all groups, chunked to bound memory):

1. Patches: all overlapping P×P×3 patches via ``F.unfold`` -> [Np, 3·P·P] (Np = (H−P+1)(W−P+1)).
2. Block matching: reference patches on a ``stride`` grid (plus the last row/column so the references
   alone cover the image); candidates on a ``search_step`` grid inside ±``search_radius`` px; squared
   distances from one batched matmul (‖c‖² − 2⟨c, r⟩; ‖r‖² is constant per reference); the ``group_size``
   nearest by a stable sort (deterministic ties). The reference is always its own first member.
3. Weighted singular value thresholding per group (SAIST / WNNM style, LR3M eq. for the R sub-problem):
   the group mean is removed (it carries the DC and is averaged, not shrunk); with n members, d = 3P²
   entries and noise σ_w, the clean singular value is estimated as
   ``σ̂_i = sqrt(max(σ_i² − (√d + √(n−1))² σ_w², 0))`` (the Marchenko–Pastur edge of an n×d noise matrix:
   pure-noise components get σ̂ = 0 and vanish) and shrunk by ``τ_i = c1·√n·σ_w² / (σ̂_i + eps)``.
   The SVD is ``torch.linalg.svd`` or, faster and mathematically identical, the eigen-decomposition of
   the n×n Gram matrix (``solver="gram"``; 5× faster on CPU for 40×147 groups).
4. Aggregation: every member patch is added back at its position and divided by the per-pixel count.
   On CUDA the sums use 64-bit fixed point so that the result is bit-identical run to run (float atomics
   would not be); on CPU ``index_add_`` is sequential and float sums are already deterministic.
"""
from __future__ import annotations

import contextlib
from typing import Iterator, Optional, Tuple

import torch
import torch.nn.functional as F

from retinexgs.kth_value import kth_smallest

_FIXED_SCALE = float(2 ** 32)  # fixed-point step 2^-32; |value| <= 64 and < 2^14 contributions fit int64
_CHUNK_ELEMS = 24_000_000  # elements per gathered chunk (~96 MB of float32)


def estimate_noise_sigma(x: torch.Tensor) -> torch.Tensor:
    """Per-image noise std of [B,C,H,W] from the finest Haar diagonal band: median(|HH|) / 0.6745.

    (Donoho's robust MAD estimator; image structure barely reaches the diagonal band at the finest scale.)
    """
    h, w = (x.shape[-2] // 2) * 2, (x.shape[-1] // 2) * 2
    v = x[..., :h, :w]
    hh = (v[..., 0::2, 0::2] - v[..., 0::2, 1::2] - v[..., 1::2, 0::2] + v[..., 1::2, 1::2]) * 0.5
    flat = hh.abs().flatten(1)
    # torch's median is the lower middle value, the ((n + 1) // 2)-th smallest: a k-th value fast on the GPU (its median
    # selects in one thread block per slice, as kthvalue, which took 70 ms for 12 M values; retinexgs/kth_value.py)
    return kth_smallest(flat, (flat.shape[1] + 1) // 2, dim=1) / 0.6745


def reference_grid(h: int, w: int, patch: int, stride: int, device: torch.device) -> Tuple[torch.Tensor, torch.Tensor]:
    """Top-left corners (y, x) of the reference patches, flattened row-major: two [Nref] long tensors."""
    def axis(n: int) -> torch.Tensor:
        last = n - patch
        pos = list(range(0, last + 1, stride))
        if pos[-1] != last:
            pos.append(last)  # cover the border
        return torch.tensor(pos, device=device, dtype=torch.long)
    ys, xs = axis(h), axis(w)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return gy.reshape(-1), gx.reshape(-1)


def _patches(img: torch.Tensor, patch: int) -> torch.Tensor:
    """[C,H,W] -> all patches as rows [Np, C·P·P] (unfold order: channel, row, column)."""
    return F.unfold(img.unsqueeze(0), patch)[0].t().contiguous()


def block_match(guide: torch.Tensor, patch: int = 7, stride: int = 6, search_radius: int = 25,
                search_step: int = 2, group_size: int = 40) -> torch.Tensor:
    """Indices of the ``group_size`` most similar patches for every reference patch of a [C,H,W] guide.

    Returns [Nref, n] long indices into the (H−P+1)×(W−P+1) patch grid, reference first.
    """
    c, h, w = guide.shape
    hp, wp = h - patch + 1, w - patch + 1
    dev = guide.device
    pt = _patches(guide, patch)
    sqn = (pt * pt).sum(1)
    ry, rx = reference_grid(h, w, patch, stride, dev)
    ref_idx = ry * wp + rx
    reach = (search_radius // search_step) * search_step
    steps = torch.arange(-reach, reach + 1, search_step, device=dev)
    oy, ox = torch.meshgrid(steps, steps, indexing="ij")
    oy, ox = oy.reshape(-1), ox.reshape(-1)
    n_off = oy.numel()
    zero = int(torch.nonzero((oy == 0) & (ox == 0))[0])
    n = min(group_size, n_off)
    out = torch.empty(ry.numel(), n, dtype=torch.long, device=dev)
    chunk = max(1, _CHUNK_ELEMS // (n_off * pt.shape[1]))
    for a in range(0, ry.numel(), chunk):
        b = min(a + chunk, ry.numel())
        cy = ry[a:b, None] + oy[None]
        cx = rx[a:b, None] + ox[None]
        valid = (cy >= 0) & (cy < hp) & (cx >= 0) & (cx < wp)
        cidx = torch.where(valid, cy * wp + cx, ref_idx[a:b, None])
        dots = torch.bmm(pt[cidx], pt[ref_idx[a:b]].unsqueeze(-1)).squeeze(-1)
        dist = sqn[cidx] - 2.0 * dots
        dist = dist.masked_fill(~valid, float("inf"))
        dist[:, zero] = -float("inf")  # the reference itself leads its group despite rounding
        order = torch.sort(dist, dim=1, stable=True).indices[:, :n]
        out[a:b] = torch.gather(cidx, 1, order)  # invalid picks (tiny images) fall back to the reference
    return out


@contextlib.contextmanager
def _linalg_threads(device: torch.device) -> Iterator[None]:
    """Run batched CPU LAPACK calls on one thread.

    Many tiny eigh/svd calls gain nothing from intra-op threads, and when the cores are shared the
    per-call thread barriers made them 10-100x slower (measured: 0.6 s -> 58 s for 6420 40×40 eighs).
    """
    if device.type != "cpu":
        yield
        return
    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(prev)


def _shrink_groups(y: torch.Tensor, sigma_w: torch.Tensor, c1: float, solver: str) -> torch.Tensor:
    """Weighted singular value thresholding of centred groups y [G,n,d] with noise sigma_w [G]."""
    g, n, d = y.shape
    s2 = sigma_w.view(-1, 1) ** 2
    edge = (d ** 0.5 + max(n - 1, 1) ** 0.5) ** 2  # Marchenko–Pastur edge of the centred noise matrix
    with _linalg_threads(y.device):
        if solver == "svd":
            u, s, vh = torch.linalg.svd(y, full_matrices=False)
        else:
            evals, u = torch.linalg.eigh(y @ y.transpose(1, 2))  # y yᵀ = U S² Uᵀ
            s = evals.clamp_min(0).sqrt()
    sx = (s * s - edge * s2).clamp_min(0).sqrt()
    tau = c1 * (n ** 0.5) * s2 / (sx + 1e-8)
    s_new = (s - tau).clamp_min(0)
    if solver == "svd":
        return (u * s_new.unsqueeze(1)) @ vh
    factor = torch.where(s > 1e-12, s_new / s.clamp_min(1e-12), torch.zeros_like(s))
    return (u * factor.unsqueeze(1)) @ (u.transpose(1, 2) @ y)  # U diag(s'/s) Uᵀ y = U diag(s') Vᵀ


def lowrank_denoise(img: torch.Tensor, groups: torch.Tensor, sigma_ref: torch.Tensor, patch: int = 7,
                    c1: float = 2.9 * 2 ** 0.5, solver: str = "gram") -> torch.Tensor:
    """Low-rank estimate of a [C,H,W] image from precomputed ``groups`` ([Nref,n] from :func:`block_match`).

    ``sigma_ref`` [Nref] is the noise std assumed for each group. Returns a [C,H,W] image.
    """
    c, h, w = img.shape
    wp = w - patch + 1
    dev = img.device
    pt = _patches(img, patch)
    d = pt.shape[1]
    # Offsets of a patch's entries in the flattened [C*H*W] image, in unfold order.
    cc, ky, kx = torch.meshgrid(torch.arange(c, device=dev), torch.arange(patch, device=dev),
                                torch.arange(patch, device=dev), indexing="ij")
    offs = (cc * h * w + ky * w + kx).reshape(-1)
    # CPU index_add_ is sequential, hence deterministic, in float. CUDA uses atomics, whose float sums
    # depend on thread order: there we add 64-bit fixed-point integers, which is exact and order-free.
    fixed = dev.type != "cpu"
    acc = torch.zeros(c * h * w, dtype=torch.long if fixed else torch.float32, device=dev)
    cnt = torch.zeros(c * h * w, dtype=torch.int32 if not fixed else torch.long, device=dev)
    n_ref, n = groups.shape
    chunk = max(1, _CHUNK_ELEMS // (n * d))
    for a in range(0, n_ref, chunk):
        b = min(a + chunk, n_ref)
        idx = groups[a:b]
        grp = pt[idx]  # [G,n,d]
        mean = grp.mean(dim=1, keepdim=True)
        est = _shrink_groups(grp - mean, sigma_ref[a:b], c1, solver) + mean
        base = (idx // wp) * w + (idx % wp)
        tgt = (base.unsqueeze(-1) + offs).reshape(-1)
        vals = est.reshape(-1).to(torch.float32)
        if fixed:
            vals = (vals.clamp(-64.0, 64.0) * _FIXED_SCALE).round().to(torch.long)
        acc.index_add_(0, tgt, vals)
        cnt.index_add_(0, tgt, torch.ones(1, dtype=cnt.dtype, device=dev).expand(tgt.numel()))
    if fixed:
        out = (acc.to(torch.float64) / (_FIXED_SCALE * cnt.clamp_min(1).to(torch.float64))).to(img.dtype)
    else:
        out = acc / cnt.clamp_min(1).to(acc.dtype)
    # Pixels no group touched cannot occur (references cover the image) but keep the input there anyway.
    out = torch.where(cnt > 0, out.to(img.dtype), img.reshape(-1))
    return out.view(c, h, w)


def group_noise(sigma_map: torch.Tensor, patch: int, stride: int) -> torch.Tensor:
    """Mean of a per-pixel noise map [1,H,W] over each reference patch -> [Nref]."""
    h, w = sigma_map.shape[-2:]
    pooled = F.avg_pool2d(sigma_map.unsqueeze(0), patch, stride=1)[0, 0]  # [Hp,Wp]
    ry, rx = reference_grid(h, w, patch, stride, sigma_map.device)
    return pooled[ry, rx]


def lowrank_step(img: torch.Tensor, sigma_map: torch.Tensor, groups: Optional[torch.Tensor], guide: torch.Tensor,
                 patch: int, stride: int, search_radius: int, search_step: int, group_size: int, c1: float,
                 solver: str) -> Tuple[torch.Tensor, torch.Tensor]:
    """One low-rank pass on [C,H,W] ``img``; matches on ``guide`` unless ``groups`` is given.

    Returns (denoised image, groups) so that callers can reuse the matching.
    """
    if groups is None:
        groups = block_match(guide, patch, stride, search_radius, search_step, group_size)
    sig = group_noise(sigma_map, patch, stride)
    return lowrank_denoise(img, groups, sig, patch, c1, solver), groups
