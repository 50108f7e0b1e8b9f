"""The public rendering API: :func:`rasterize_gaussians` and :func:`spherical_harmonics`."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from retinexgs.render.camera import Camera
from retinexgs.render.functions import ProjectGaussians, RasterizeGaussians, SphericalHarmonics, bin_gaussians
from retinexgs.render.pair_budget import PairBudget
from retinexgs.render.validate import check_gaussians, check_tensor, gaussian_tensors, raise_if_not_finite

MAX_CUDA_CHANNELS = 64  # rgs::kMaxCudaChannels: register-resident accumulators of the CUDA compositing


@dataclass
class RenderOutput:
    """What one render returns.

    Attributes:
        image: [H, W, C] composited channels (plus ``(1 - alpha) * background`` when a background is given).
        alpha: [H, W, 1] accumulated opacity.
        depth: [H, W, 1] alpha-weighted camera depth Σ wᵢ zᵢ (divide by alpha for the expected depth), or None.
        means2d: [N, 2] projected centres in pixels; its ``.grad`` after backward is the screen-space gradient
            used by densification (kept with ``retain_grad`` when it requires grad).
        radii: [N, 2] int32 pixel half extents; 0 marks Gaussians culled in this view.
        num_pairs: number of (tile, Gaussian) pairs rasterized: the tiles of each Gaussian's rectangle where it
            can reach alpha >= 1/255 (tile culling); None when binned without a host sync (``pairs``), where
            the count stays on the device.
        packed: with ``rasterize_gaussians(packed=True)``, [H, W, C (+1) + 1]: image, depth (if rendered) and
            alpha as one tensor, of which the three above are views; else None.
    """

    image: Tensor
    alpha: Tensor
    depth: Optional[Tensor]
    means2d: Tensor
    radii: Tensor
    num_pairs: Optional[int]
    packed: Optional[Tensor] = None

    @property
    def visible(self) -> Tensor:
        """[N] bool mask of the Gaussians that were not culled."""
        return (self.radii > 0).all(dim=-1)


def rasterize_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    camera: Camera,
    *,
    background: Optional[Tensor] = None,
    render_depth: bool = False,
    validate: bool = True,
    pairs: Optional[PairBudget] = None,
    packed: bool = False,
) -> RenderOutput:
    """Render N 3D Gaussians with C-channel colours from one camera, differentiably.

    Runs projection (EWA splatting with the 0.3 low-pass), 16×16 tile binning and front-to-back alpha
    compositing on the tensors' device: the OpenMP CPU kernels for CPU tensors, the CUDA kernels for CUDA
    tensors. Gradients flow to ``means``, ``quats``, ``scales``, ``opacities`` and ``colors``.

    Args:
        means: [N, 3] centres in world space (float32 or float64; all inputs share dtype and device).
        quats: [N, 4] rotations as (w, x, y, z); normalised inside, so any non-zero norm works; a zero
            quaternion means the identity rotation and gets a zero gradient.
        scales: [N, 3] standard deviations along the Gaussian's axes (already exponentiated).
        opacities: [N] in [0, 1] (already through a sigmoid); alpha is clamped to 0.99, and a Gaussian with
            opacity <= 1/255 is culled.
        colors: [N, C] per-Gaussian channels, any C >= 1 (e.g. 3 for RGB; RetinexGS renders 6).
        camera: the :class:`~retinexgs.render.Camera` (world-to-camera, intrinsics, size, near/far).
        background: optional [C] colour composited behind the Gaussians.
        render_depth: also render the alpha-weighted depth map.
        validate: check that every tensor is finite (a NaN or inf anywhere raises a ValueError naming the
            argument). The projection checks them as it reads them and the verdict is read right after
            binning's own host sync, so the check costs no pass and no sync of its own; a loop that checks its
            parameters itself (the trainer does, every step) passes False.
            Shapes, dtypes and devices are always checked.
        pairs: a :class:`~retinexgs.render.pair_budget.PairBudget` (a training loop's): bin without a host sync
            into a pair buffer it sizes (the GPU then never waits for the host in a render); needs
            ``validate=False``, whose verdict is read after the synced binning.
        packed: also return image, depth and alpha as one tensor (``RenderOutput.packed``), written so by the
            compositing: a loss that takes them together needs no concatenation, and its gradient reaches the
            compositing as it is.

    Returns:
        A :class:`RenderOutput` with ``image`` [H, W, C], ``alpha`` [H, W, 1], ``depth`` [H, W, 1] or None,
        ``means2d``, ``radii`` and ``num_pairs``.
    """
    # The finiteness check rides on the projection, which reads every Gaussian anyway (no pass of its own), and
    # its verdict is read after binning, which waits for the GPU for its pair count: no extra sync either. The
    # projection culls non-finite Gaussians, so binning is safe on such input.
    if pairs is not None and validate:
        raise ValueError("rasterize_gaussians: pairs (binning without a host sync) needs validate=False")
    check_gaussians(means, quats, scales, opacities, colors, camera, background, finite=False)
    means2d, depths, conics, radii, nonfinite = ProjectGaussians.apply(
        means, quats, scales, opacities, camera, validate, colors.detach() if validate else None,
        background.detach() if validate and background is not None else None)
    verdict, copied = nonfinite, None
    if validate and means.is_cuda:
        verdict = torch.empty(1, dtype=torch.int32, pin_memory=True)
        verdict.copy_(nonfinite, non_blocking=True)
        copied = torch.cuda.Event()
        copied.record()
    if means2d.requires_grad:
        means2d.retain_grad()
    # conics and opacities: pairs only with the tiles each Gaussian can reach (the compositing gets the same ones).
    size = (camera.width, camera.height)
    capacity = pairs.plan(means.shape[0], means.device, size) if pairs is not None else None
    if capacity is None:
        gauss_ids, tile_ranges = bin_gaussians(means2d, radii, depths, camera.width, camera.height, conics,
                                               opacities)
        num_pairs: Optional[int] = int(gauss_ids.shape[0])
        if pairs is not None:
            pairs.observe_synced(num_pairs)
    else:
        count = torch.empty(1, dtype=torch.int64, device=means.device)
        gauss_ids, tile_ranges = bin_gaussians(means2d, radii, depths, camera.width, camera.height, conics,
                                               opacities, capacity=capacity, count=count)
        pairs.observe(count, capacity)
        num_pairs = None  # on the device only: reading it would be the sync this path avoids
    if validate:
        if copied is not None:
            copied.synchronize()  # done already: binning has waited for the stream
        if int(verdict[0]) != 0:
            raise_if_not_finite(False, gaussian_tensors(means, quats, scales, opacities, colors, background))
    channels = torch.cat([colors, depths.unsqueeze(-1)], dim=-1) if render_depth else colors
    if means.is_cuda and channels.shape[1] > MAX_CUDA_CHANNELS:
        raise ValueError(f"colors has {colors.shape[1]} channels{' + depth' if render_depth else ''}; the CUDA "
                         f"compositing supports at most {MAX_CUDA_CHANNELS} (render in chunks of channels)")
    # The background closes the colours' channels inside the compositing (not the depth's): no pass of its own.
    image, alpha = RasterizeGaussians.apply(means2d, conics, channels, opacities, gauss_ids, tile_ranges,
                                            camera.width, camera.height, background, packed)
    whole, depth = (image if packed else None), None
    if render_depth or packed:
        # split, not slices: its backward is one concatenation, each slice's a zero-filled full-size tensor
        parts = image.split([colors.shape[1]] + [1] * (int(render_depth) + int(packed)), dim=-1)
        image, depth = parts[0], (parts[1] if render_depth else None)
        if packed:
            alpha = parts[-1]
    return RenderOutput(image, alpha, depth, means2d, radii, num_pairs, whole)


def spherical_harmonics(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Evaluate real spherical harmonics (the 3DGS basis) of ``degree`` 0..3.

    Args:
        degree: active SH degree; only the first (degree + 1)² bases of ``coeffs`` are used.
        dirs: [N, 3] view directions (normalised inside; gradients flow through the normalisation).
        coeffs: [N, K, D] coefficients, K >= (degree + 1)².

    Returns:
        [N, D] values Σₖ Bₖ(dir) coeffs[:, k]. (3DGS adds 0.5 and clamps at 0 to get a colour.)
    """
    if isinstance(degree, bool) or not isinstance(degree, int) or not 0 <= degree <= 3:
        raise ValueError(f"degree must be an integer in 0..3, got {degree!r}")
    check_tensor(coeffs, "coeffs", (None, None, None))
    if coeffs.shape[1] < (degree + 1) ** 2:
        raise ValueError(f"coeffs has {coeffs.shape[1]} bases but degree {degree} needs {(degree + 1) ** 2}")
    check_tensor(dirs, "dirs", (coeffs.shape[0], 3), coeffs)
    return SphericalHarmonics.apply(degree, dirs, coeffs)
