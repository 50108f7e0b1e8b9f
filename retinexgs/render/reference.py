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
from retinexgs.render.rotation import quat_to_rotmat

TILE = 16
ALPHA_MAX, ALPHA_MIN, T_MIN, LOW_PASS, GUARD = 0.99, 1.0 / 255.0, 1e-4, 0.3, 1.3

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


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


# 1 / (2k + 1), k = 11..1, and ln 2: the literals of rgs::log_rn.
_LOG_SERIES = (0.043478260869565216, 0.047619047619047616, 0.05263157894736842, 0.058823529411764705,
               0.06666666666666667, 0.07692307692307693, 0.09090909090909091, 0.1111111111111111,
               0.14285714285714285, 0.2, 0.3333333333333333, 1.0)
_LN2 = 0.69314718055994530942


def log_rn(x: Tensor) -> Tensor:
    """ln of a float64 tensor (finite, > 0) with the operations of rgs::log_rn, so the same bits as the kernels:
    x = m 2^e, m in [√½, √2), ln m = 2 atanh((m - 1) / (m + 1)) by its series."""
    m, e = torch.frexp(x)
    low = m < 0.70710678118654752440
    m = torch.where(low, m * 2.0, m)
    e = torch.where(low, e - 1, e).double()
    s = (m - 1.0) / (m + 1.0)
    s2 = s * s
    p = torch.full_like(s, _LOG_SERIES[0])
    for c in _LOG_SERIES[1:]:
        p = p * s2 + c
    return e * _LN2 + 2.0 * s * p


def _tile_pair_mask_rows(means2d: Tensor, conics: Tensor, opacities: Tensor, rect: Tensor, tiles_x: int,
                         tiles_y: int) -> Tensor:
    """[n, tiles] bool for n Gaussians with tile rectangles ``rect`` [n, 4]: the pairs rgs::TileReach keeps."""
    t = torch.arange(tiles_x * tiles_y, device=means2d.device)
    tx, ty = (t % tiles_x).unsqueeze(0), (t // tiles_x).unsqueeze(0)
    in_rect = (tx >= rect[:, :1]) & (tx < rect[:, 2:3]) & (ty >= rect[:, 1:2]) & (ty < rect[:, 3:4])
    m = means2d.detach().double()
    mx, my = m[:, :1], m[:, 1:]
    x0 = (tx * TILE).double() + 0.5
    x1 = x0 + (TILE - 1)
    y0 = (ty * TILE).double() + 0.5
    y1 = y0 + (TILE - 1)
    inside = (mx >= x0) & (mx <= x1) & (my >= y0) & (my <= y1)
    c = conics.detach().double()
    shrink = 1.0 - 2e-5
    A, B, C = c[:, :1] * shrink, c[:, 1:2], c[:, 2:] * shrink
    level = 255.0 * opacities.detach().double().unsqueeze(1)
    keep_all = ~((level > 1.0) & (level <= 1e300) & (A > 0) & (C > 0) & (A * C - B * B > 0) & (A <= 1e300)
                 & (C <= 1e300) & (mx - mx == 0) & (my - my == 0))
    ok = ~keep_all  # the kernels compute 1/A, 1/C and the log only there
    one = torch.ones_like(A)
    rA, rC = 1.0 / torch.where(ok, A, one), 1.0 / torch.where(ok, C, one)
    cut = log_rn(torch.where(ok, level, one * 2.0)) + 2e-3

    def q(dx: Tensor, dy: Tensor) -> Tensor:
        return 0.5 * (A * dx * dx + C * dy * dy) + B * dx * dy

    def clamp(v: Tensor, lo: Tensor, hi: Tensor) -> Tensor:  # v < lo ? lo : (v > hi ? hi : v), NaN stays
        return torch.where(v < lo, lo, torch.where(v > hi, hi, v))

    best = None
    for X in (x0, x1):  # edges x = x0, x1: minimiser over dy clamped to the box
        dx = X - mx
        s = q(dx, clamp(-B * dx * rC, y0 - my, y1 - my))
        best = s if best is None else torch.where(s < best, s, best)
    for Y in (y0, y1):
        dy = Y - my
        s = q(clamp(-B * dy * rA, x0 - mx, x1 - mx), dy)
        best = torch.where(s < best, s, best)
    return in_rect & (keep_all | inside | ~(best > cut))


def _pair_mask_chunks(means2d: Tensor, conics: Tensor, opacities: Tensor, radii: Tensor, width: int, height: int):
    """Yields the rows of :func:`tile_pair_mask`, a few Gaussians at a time (about 2^20 entries each)."""
    tiles_x, tiles_y = math.ceil(width / TILE), math.ceil(height / TILE)
    rect = tile_rects(means2d, radii, width, height)
    step = max(1, (1 << 20) // (tiles_x * tiles_y))
    for s in range(0, means2d.shape[0], step):
        yield _tile_pair_mask_rows(means2d[s:s + step], conics[s:s + step], opacities[s:s + step],
                                   rect[s:s + step], tiles_x, tiles_y)


def tile_pair_mask(means2d: Tensor, conics: Tensor, opacities: Tensor, radii: Tensor, width: int,
                   height: int) -> Tensor:
    """[N, tiles] bool: the (Gaussian, tile) pairs the binning keeps (``bin_gaussians`` with conics and
    opacities). A tile of the Gaussian's rectangle is kept unless alpha < 1/255 at all its pixel centres by the
    conservative test of rgs::TileReach, with the same float64 operations: the minimum over the box of the tile's
    pixel centres of ½ (1 - 2e-5)(A dx² + C dy²) + B dx dy must exceed ln(255 o) + 2e-3."""
    rows = list(_pair_mask_chunks(means2d, conics, opacities, radii, width, height))
    if not rows:
        return torch.zeros(0, math.ceil(width / TILE) * math.ceil(height / TILE), dtype=torch.bool,
                           device=means2d.device)
    return torch.cat(rows)


def count_tile_pairs_reference(means2d: Tensor, conics: Tensor, opacities: Tensor, radii: Tensor, width: int,
                               height: int) -> int:
    """Number of (tile, Gaussian) pairs the binning makes: ``tile_pair_mask(...).sum()`` in bounded memory."""
    return sum(int(rows.sum()) for rows in _pair_mask_chunks(means2d, conics, opacities, radii, width, height))


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
    pairs = count_tile_pairs_reference(means2d, conics, opacities, radii, camera.width, camera.height)
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
