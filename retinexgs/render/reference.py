"""Pure-torch twin of the renderer: dense, slow and written to be obviously right. Tests compare the
kernels against it; autograd differentiates it. It mirrors the kernels' conventions exactly (guard band,
opacity-aware extents, tile culling, α ≤ 0.99, skip α < 1/255, stop before T < 1e-4)."""
from __future__ import annotations

import math
from typing import Optional, Tuple

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from retinexgs.render.camera import Camera
from retinexgs.render.rasterize import RenderOutput
from retinexgs.render.validate import check_gaussians

TILE = 16
ALPHA_MAX, ALPHA_MIN, T_MIN, LOW_PASS, GUARD = 0.99, 1.0 / 255.0, 1e-4, 0.3, 1.3

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] (w, x, y, z) -> [N, 3, 3]; a zero quaternion gives the identity."""
    n = quats.norm(dim=-1, keepdim=True)
    q = torch.where(n > 1e-12, quats / n.clamp_min(1e-12), torch.zeros_like(quats))
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def project_reference(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                      camera: Camera) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Projection: means2d [N,2], depths [N], conics [N,3] (A, B, C), radii [N,2] int32 (0 = culled)."""
    vm = camera.viewmat.to(means)
    W, t = vm[:3, :3], vm[:3, 3]
    p = means @ W.T + t
    x, y, z = p.unbind(-1)
    R = quat_to_rotmat(quats)
    M = R * scales.unsqueeze(-2)
    sigma_cam = W @ (M @ M.transpose(-1, -2)) @ W.T
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    zs = torch.where(z.abs() > 1e-12, z, torch.ones_like(z))  # culled anyway; avoids inf in the graph
    u = torch.clamp(x / zs, -GUARD * cx / fx, GUARD * (camera.width - cx) / fx)
    v = torch.clamp(y / zs, -GUARD * cy / fy, GUARD * (camera.height - cy) / fy)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / zs, zero, -fx * u / zs, zero, fy / zs, -fy * v / zs], -1).reshape(-1, 2, 3)
    cov = J @ sigma_cam @ J.transpose(-1, -2) + LOW_PASS * torch.eye(2, dtype=means.dtype, device=means.device)
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    dets = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([c / dets, -b / dets, a / dets], -1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)
    with torch.no_grad():
        level = 255.0 * opacities
        k = torch.sqrt(2 * torch.log(level.clamp_min(1.0)))
        ex, ey = k * a.clamp_min(0).sqrt(), k * c.clamp_min(0).sqrt()
        mx, my = means2d.unbind(-1)
        keep = (z >= camera.near) & (z <= camera.far) & (det > 0) & (level > 1)
        keep &= (mx + ex > 0) & (mx - ex < camera.width) & (my + ey > 0) & (my - ey < camera.height)
        keep &= (ex < 1e7) & (ey < 1e7)
        radii = torch.stack([torch.ceil(ex), torch.ceil(ey)], -1)
        keep &= (radii > 0).all(-1)
        radii = torch.where(keep.unsqueeze(-1), radii, torch.zeros_like(radii)).to(torch.int32)
    keep2 = keep.unsqueeze(-1)
    means2d = torch.where(keep2, means2d, torch.zeros_like(means2d))
    conics = torch.where(keep2, conics, torch.zeros_like(conics))
    depths = torch.where(keep, z, torch.zeros_like(z))
    return means2d, depths, conics, radii


def tile_rects(means2d: Tensor, radii: Tensor, width: int, height: int) -> Tensor:
    """[N, 4] tile rectangles (x0, y0, x1, y1), half-open, as the binning computes them."""
    tiles_x, tiles_y = math.ceil(width / TILE), math.ceil(height / TILE)
    m = means2d.detach().double()
    r = radii.double()
    x0 = torch.floor((m[:, 0] - r[:, 0] - 1.5) / TILE).clamp(0, tiles_x)
    x1 = (torch.floor((m[:, 0] + r[:, 0] + 0.5) / TILE) + 1).clamp(0, tiles_x)
    y0 = torch.floor((m[:, 1] - r[:, 1] - 1.5) / TILE).clamp(0, tiles_y)
    y1 = (torch.floor((m[:, 1] + r[:, 1] + 0.5) / TILE) + 1).clamp(0, tiles_y)
    visible = (radii > 0).all(-1)
    rect = torch.stack([x0, y0, torch.maximum(x1, x0), torch.maximum(y1, y0)], -1).long()
    return torch.where(visible.unsqueeze(-1), rect, torch.zeros_like(rect))


def composite_reference(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, depths: Tensor,
                        radii: Tensor, width: int, height: int,
                        chunk: Optional[int] = None) -> Tuple[Tensor, Tensor]:
    """Dense front-to-back compositing: image [H,W,C] and alpha [H,W,1]. ``chunk`` pixels at a time (default:
    about 2^20 pixel-Gaussian entries per intermediate, small enough for the allocator to reuse memory
    instead of mapping fresh pages for every chunk)."""
    # float32 depth, ties by index: the kernels' sort order (rgs::sort_depth), in every dtype.
    order = torch.argsort(depths.detach().float(), stable=True)
    visible = (radii > 0).all(-1)
    order = order[visible[order]]
    m, cn, col, op = means2d[order], conics[order], colors[order], opacities[order]
    rect = tile_rects(means2d, radii, width, height)[order]
    ys, xs = torch.meshgrid(torch.arange(height, device=m.device), torch.arange(width, device=m.device),
                            indexing="ij")
    xs, ys = xs.reshape(-1), ys.reshape(-1)
    if chunk is None:
        chunk = max(16, (1 << 20) // max(1, int(m.shape[0])))
    images, alphas = [], []
    # Under autograd each chunk is checkpointed (recomputed in backward): otherwise every chunk's
    # [pixels x Gaussians] intermediates stay alive until backward, which for 1e4 Gaussians at 500x375 is
    # over 100 GB.
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (m, cn, col, op))
    for s in range(0, xs.shape[0], chunk):
        px, py = xs[s:s + chunk], ys[s:s + chunk]
        if needs_grad:
            image, alpha = checkpoint(_composite_chunk, px, py, m, cn, col, op, rect, use_reentrant=False)
        else:
            image, alpha = _composite_chunk(px, py, m, cn, col, op, rect)
        images.append(image)
        alphas.append(alpha)
    return torch.cat(images).reshape(height, width, -1), torch.cat(alphas).reshape(height, width, 1)


def _composite_chunk(px: Tensor, py: Tensor, m: Tensor, cn: Tensor, col: Tensor, op: Tensor,
                     rect: Tensor) -> Tuple[Tensor, Tensor]:
    """Colour [P,C] and alpha [P,1] of pixels (px, py) [P] over depth-sorted Gaussians (dense)."""
    tx, ty = (px // TILE).unsqueeze(1), (py // TILE).unsqueeze(1)
    in_tile = (tx >= rect[:, 0]) & (tx < rect[:, 2]) & (ty >= rect[:, 1]) & (ty < rect[:, 3])
    dx = px.to(m.dtype).unsqueeze(1) + 0.5 - m[:, 0]
    dy = py.to(m.dtype).unsqueeze(1) + 0.5 - m[:, 1]
    sigma = 0.5 * (cn[:, 0] * dx * dx + cn[:, 2] * dy * dy) + cn[:, 1] * dx * dy
    alpha = torch.clamp(op * torch.exp(-sigma), max=ALPHA_MAX)
    alpha = torch.where(in_tile & (sigma >= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    T_before = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
    stops = (T_before * (1 - alpha) < T_MIN) & (alpha > 0)
    included = torch.cumsum(stops.int(), 1) == 0
    w = torch.where(included, alpha * T_before, torch.zeros_like(alpha))
    return w @ col, w.sum(1, keepdim=True)


def rasterize_gaussians_reference(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
                                  camera: Camera, *, background: Optional[Tensor] = None,
                                  render_depth: bool = False) -> RenderOutput:
    """Pure-torch version of :func:`retinexgs.render.rasterize_gaussians` (same arguments and outputs)."""
    check_gaussians(means, quats, scales, opacities, colors, camera, background)
    means2d, depths, conics, radii = project_reference(means, quats, scales, opacities, camera)
    channels = torch.cat([colors, depths.unsqueeze(-1)], -1) if render_depth else colors
    image, alpha = composite_reference(means2d, conics, channels, opacities, depths, radii, camera.width,
                                       camera.height)
    depth = None
    if render_depth:
        image, depth = image[..., :-1], image[..., -1:]
    if background is not None:
        image = image + (1.0 - alpha) * background
    rect = tile_rects(means2d, radii, camera.width, camera.height)
    pairs = int(((rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1])).sum())
    return RenderOutput(image, alpha, depth, means2d, radii, pairs)


def sh_basis_reference(degree: int, dirs: Tensor) -> Tensor:
    """[N, (degree+1)²] real SH basis at the normalised directions."""
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = d.unbind(-1)
    B = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        B += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        B += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
              SH_C2[4] * (xx - yy)]
    if degree >= 3:
        B += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * zz - xx - yy),
              SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
              SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(B, -1)


def spherical_harmonics_reference(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Pure-torch version of :func:`retinexgs.render.spherical_harmonics`."""
    B = sh_basis_reference(degree, dirs)
    return torch.einsum("nk,nkd->nd", B, coeffs[:, : B.shape[1]])
