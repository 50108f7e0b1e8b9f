"""``torch.autograd.Function`` wrappers of the kernels: each forward calls ``retinexgs._C``, each backward
calls the matching analytic gradient kernel. Shapes: N Gaussians, C channels, K SH bases, D SH channels."""
from __future__ import annotations

from typing import Optional, Tuple

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from retinexgs.render._backend import kernels
from retinexgs.render.camera import Camera


class ProjectGaussians(torch.autograd.Function):
    """(means [N,3], quats [N,4], scales [N,3], opacities [N]) -> means2d [N,2], depths [N], conics [N,3],
    radii [N,2] int32, nonfinite. Differentiable in means, quats and scales (opacity only sets the extent).

    With ``check_finite`` the projection also checks its inputs, ``colors`` [N,C] and ``background`` [C] (plain
    tensors, not differentiated through here) for NaN/inf: ``nonfinite`` is an int32 [1] tensor on their device,
    0 when all are finite, nothing waiting for it; otherwise ``nonfinite`` is None."""

    @staticmethod
    def forward(ctx, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, camera: Camera,
                check_finite: bool = False, colors: Optional[Tensor] = None, background: Optional[Tensor] = None):
        means2d, depths, conics, radii, nonfinite = kernels().project_forward(
            means, quats, scales, opacities, *camera.kernel_args, check_finite, colors, background)
        ctx.camera = camera
        ctx.save_for_backward(means, quats, scales, radii)
        ctx.mark_non_differentiable(radii)
        if nonfinite is not None:
            ctx.mark_non_differentiable(nonfinite)
        return means2d, depths, conics, radii, nonfinite

    @staticmethod
    @once_differentiable
    def backward(ctx, v_means2d: Tensor, v_depths: Tensor, v_conics: Tensor, _v_radii, _v_nonfinite):
        means, quats, scales, radii = ctx.saved_tensors
        v_means, v_quats, v_scales = kernels().project_backward(
            means, quats, scales, *ctx.camera.kernel_args, radii, v_means2d, v_depths, v_conics)
        return v_means, v_quats, v_scales, None, None, None, None, None


def bin_gaussians(means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int,
                  conics: Optional[Tensor] = None, opacities: Optional[Tensor] = None,
                  capacity: Optional[int] = None, count: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
    """Tile binning (not differentiable): the Gaussian index of every (tile, Gaussian) pair, ordered by tile
    then depth, [M] int32; and each tile's [begin, end) range into it, [tiles, 2] int32.

    A Gaussian pairs with the tiles of its bounding rectangle (from ``radii``); given ``conics`` [N, 3] and
    ``opacities`` [N] too (the ones the compositing will get), only with those where it can reach alpha >= 1/255
    at some pixel centre. The others would composite nothing: same image and gradients, fewer pairs.

    ``capacity`` (with ``count``, an int64 [1] tensor on the same device): binning without a host sync on the
    GPU. The ids are [capacity] long; M is written into ``count`` on the device; if M > capacity the pairs at
    offsets >= capacity (the highest-index Gaussians') are dropped; the ranges cover the min(M, capacity) stored
    pairs and the ids past them are -1 (:class:`retinexgs.render.pair_budget.PairBudget` picks the capacity)."""
    if (conics is None) != (opacities is None):
        raise ValueError("pass both conics and opacities to bin_gaussians, or neither")
    if (capacity is None) != (count is None):
        raise ValueError("pass both capacity and count to bin_gaussians, or neither")
    if capacity is not None and not 0 <= capacity < 2 ** 31:
        raise ValueError(f"capacity must be in 0..2**31-1 (int32 pair indices), got {capacity}")
    cull = () if conics is None else (conics.detach(), opacities.detach())
    if capacity is None:
        return kernels().bin_gaussians(means2d.detach(), radii, depths.detach(), width, height, *cull)
    return kernels().bin_gaussians(means2d.detach(), radii, depths.detach(), width, height, *(cull or (None, None)),
                                   capacity, count)


class RasterizeGaussians(torch.autograd.Function):
    """Alpha compositing of binned 2D Gaussians into an [H,W,C] image and its [H,W,1] alpha.

    ``background`` [K] (K <= C) closes the first K channels: out = Σ wᵢcᵢ + T·background, inside the kernel.
    ``alpha_channel``: one [H,W,C+1] tensor whose last channel is the alpha, and None in the alpha's place (a loss
    that wants [channels, alpha] together reads it as it is: no concatenation forward or backward)."""

    @staticmethod
    def forward(ctx, means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, gauss_ids: Tensor,
                tile_ranges: Tensor, width: int, height: int, background: Optional[Tensor] = None,
                alpha_channel: bool = False):
        bg = None if background is None else background.detach()
        image, transmittance, last_ids = kernels().rasterize_forward(means2d, conics, colors, opacities, gauss_ids,
                                                                     tile_ranges, width, height, bg, alpha_channel)
        ctx.size = (width, height)
        ctx.alpha_channel = alpha_channel
        ctx.save_for_backward(means2d, conics, colors, opacities, gauss_ids, tile_ranges, transmittance, last_ids, bg)
        if alpha_channel:
            return image, None
        return image, (1.0 - transmittance).unsqueeze(-1)

    @staticmethod
    @once_differentiable
    def backward(ctx, v_image: Tensor, v_alpha: Optional[Tensor]):
        means2d, conics, colors, opacities, gauss_ids, tile_ranges, transmittance, last_ids, bg = ctx.saved_tensors
        width, height = ctx.size
        if v_image is None:
            C = colors.shape[1] + (1 if ctx.alpha_channel else 0)
            v_image = torch.zeros(height, width, C, dtype=colors.dtype, device=colors.device)
        v_transmittance = None if v_alpha is None else -v_alpha.squeeze(-1)  # alpha = 1 - T
        v_means2d, v_conics, v_colors, v_opacities = kernels().rasterize_backward(
            means2d, conics, colors, opacities, gauss_ids, tile_ranges, width, height, transmittance, last_ids,
            v_image, v_transmittance, bg, ctx.alpha_channel)
        v_bg = None
        if bg is not None and ctx.needs_input_grad[8]:  # d out[c] / d background[c] = T
            v_bg = torch.einsum("hwk,hw->k", v_image[..., :bg.shape[0]], transmittance)
        return v_means2d, v_conics, v_colors, v_opacities, None, None, None, None, v_bg, None


class SphericalHarmonics(torch.autograd.Function):
    """Colours [N,D] from SH coefficients [N,K,D] of degree <= 3 at view directions [N,3] (any norm)."""

    @staticmethod
    def forward(ctx, degree: int, dirs: Tensor, coeffs: Tensor):
        ctx.degree = degree
        ctx.save_for_backward(dirs, coeffs)
        return kernels().sh_forward(degree, dirs, coeffs)

    @staticmethod
    @once_differentiable
    def backward(ctx, v_colors: Tensor):
        dirs, coeffs = ctx.saved_tensors
        v_dirs, v_coeffs = kernels().sh_backward(ctx.degree, dirs, coeffs, v_colors)
        return None, v_dirs, v_coeffs
