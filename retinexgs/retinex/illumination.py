"""Structure-aware illumination estimation shared by LR3M and LIME.

Both refine an initial illumination ``L̂`` by solving (LIME eq. 8/9, LR3M's L sub-problem)

    argmin_L ‖L − L̂‖² + Σ_d ‖ sqrt(a_d) ∘ ∇_d L ‖²,   a_d = β / (|∇_d L̂| + ε)

which is one sparse SPD linear system  (I + Σ_d D_dᵀ diag(a_d) D_d) l = l̂  per image. We solve it with a
batched Jacobi-preconditioned conjugate gradient in plain torch (CPU and CUDA alike).

Choices (documented in docs/retinex.md):
- ``D_d`` are forward differences with Neumann boundaries (no difference across the image border).
- The weights are computed on L̂ normalised by its 99th percentile, so the result does not depend on the
  exposure of the photo, and on Gaussian-smoothed gradients (LIME's third weighting strategy) so that
  sensor noise in a dark L̂ does not look like structure to keep.
"""
from __future__ import annotations

import math
from typing import Tuple

import torch
import torch.nn.functional as F

from retinexgs.kth_value import kth_smallest


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of [B,C,H,W] with reflect padding (radius 3σ); identity for σ <= 0."""
    if sigma <= 0:
        return x
    radius = max(1, int(math.ceil(3.0 * sigma)))
    radius = min(radius, x.shape[-1] - 1, x.shape[-2] - 1)
    t = torch.arange(-radius, radius + 1, device=x.device, dtype=x.dtype)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    c = x.shape[1]
    y = F.pad(x, (radius, radius, 0, 0), mode="reflect")
    y = F.conv2d(y, k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    y = F.pad(y, (0, 0, radius, radius), mode="reflect")
    return F.conv2d(y, k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def grad_x(x: torch.Tensor) -> torch.Tensor:
    """Forward difference along width: [...,H,W] -> [...,H,W-1]."""
    return x[..., :, 1:] - x[..., :, :-1]


def grad_y(x: torch.Tensor) -> torch.Tensor:
    """Forward difference along height: [...,H,W] -> [...,H-1,W]."""
    return x[..., 1:, :] - x[..., :-1, :]


def grad_x_t(v: torch.Tensor) -> torch.Tensor:
    """Adjoint of :func:`grad_x`: [...,H,W-1] -> [...,H,W]."""
    vp = F.pad(v, (1, 1))
    return vp[..., :, :-1] - vp[..., :, 1:]


def grad_y_t(v: torch.Tensor) -> torch.Tensor:
    """Adjoint of :func:`grad_y`: [...,H-1,W] -> [...,H,W]."""
    vp = F.pad(v, (0, 0, 1, 1))
    return vp[..., :-1, :] - vp[..., 1:, :]


def percentile_scale(x: torch.Tensor, q: float = 0.99) -> torch.Tensor:
    """Per-image q-quantile of [B,C,H,W] as [B,1,1,1] (floored so an almost-black image stays finite)."""
    flat = x.flatten(1)
    k = max(1, min(flat.shape[1], int(round(q * flat.shape[1]))))
    # a k-th value: no size limit (torch.quantile has), exact, and fast on the GPU (retinexgs/kth_value.py)
    val = kth_smallest(flat, k, dim=1)
    return val.clamp_min(1e-4).view(-1, 1, 1, 1)


def structure_weights(l_hat: torch.Tensor, beta: float, eps: float, sigma: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """a_x, a_y = β / (|G_σ * ∇_d (L̂ / q99(L̂))| + ε) for [B,1,H,W] L̂ (LIME eq. 19-21, strategy III)."""
    ln = l_hat / percentile_scale(l_hat)
    gx = gaussian_blur(grad_x(ln), sigma) if ln.shape[-1] > 2 else grad_x(ln)
    gy = gaussian_blur(grad_y(ln), sigma) if ln.shape[-2] > 2 else grad_y(ln)
    return beta / (gx.abs() + eps), beta / (gy.abs() + eps)


def solve_structure_aware(l_hat: torch.Tensor, ax: torch.Tensor, ay: torch.Tensor, tol: float = 1e-4,
                          max_iter: int = 300, check_every: int = 10) -> torch.Tensor:
    """Solve (I + D_xᵀ diag(a_x) D_x + D_yᵀ diag(a_y) D_y) l = l̂ for a batch [B,1,H,W].

    Jacobi-preconditioned CG, all images at once; an image whose relative residual ‖r‖/‖l̂‖ falls below
    ``tol`` stops moving. Convergence is tested every ``check_every`` steps (one host sync each on CUDA).
    """
    def apply_a(v: torch.Tensor) -> torch.Tensor:
        return v + grad_x_t(ax * grad_x(v)) + grad_y_t(ay * grad_y(v))

    b = l_hat
    diag = 1.0 + F.pad(ax, (1, 0)) + F.pad(ax, (0, 1)) + F.pad(ay, (0, 0, 1, 0)) + F.pad(ay, (0, 0, 0, 1))
    inv_diag = 1.0 / diag
    bsz = b.shape[0]

    def dot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return (u * v).flatten(1).sum(1).view(bsz, 1, 1, 1)

    x = b * inv_diag  # one Jacobi step: a better start than l̂ where the weights are large
    r = b - apply_a(x)
    z = r * inv_diag
    p = z
    rz = dot(r, z)
    b_norm = dot(b, b).sqrt().clamp_min(1e-12)
    active = torch.ones_like(rz)
    for it in range(max_iter):
        ap = apply_a(p)
        pap = dot(p, ap)
        alpha = torch.where(pap > 0, rz / pap.clamp_min(1e-30), torch.zeros_like(pap)) * active
        x = x + alpha * p
        r = r - alpha * ap
        if (it + 1) % check_every == 0:
            active = (dot(r, r).sqrt() / b_norm > tol).to(r.dtype)
            if not bool(active.any()):
                break
        z = r * inv_diag
        rz_new = dot(r, z)
        beta = torch.where(rz > 0, rz_new / rz.clamp_min(1e-30), torch.zeros_like(rz))
        p = z + beta * p
        rz = rz_new
    return x


def refine_illumination(l_hat: torch.Tensor, beta: float, eps: float, sigma: float, tol: float,
                        max_iter: int) -> torch.Tensor:
    """Structure-aware refinement of an initial illumination [B,1,H,W] (weights + PCG solve)."""
    ax, ay = structure_weights(l_hat, beta, eps, sigma)
    return solve_structure_aware(l_hat, ax, ay, tol=tol, max_iter=max_iter)


def max_rgb(s: torch.Tensor) -> torch.Tensor:
    """Initial illumination L̂ = max over colour channels (LIME eq. 2): [B,3,H,W] -> [B,1,H,W]."""
    return s.amax(dim=1, keepdim=True)
