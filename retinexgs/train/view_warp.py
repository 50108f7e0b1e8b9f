"""Neighbouring training views warped into a view through the model's depth: a multi-view denoiser's average.

At night a single view's SNR is near 1 and no single-view denoiser recovers its detail; the same point was seen by
many views. Each neighbour's light is carried into the view along the rays of the model's expected depth
(Σwᵢzᵢ / α of one rasterization), kept where the neighbour's own depth agrees (not occluded there) and averaged with
the view's own light: unbiased, its noise variance divided by the count of views averaged, its detail the views'
own rather than the render's (issue 64 item 1, ``decomposer.redenoise_source: views``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor

from retinexgs.render.camera import Camera

# A source pixel counts where its own depth lies within this share of the warped point's depth: beyond it the
# neighbour sees something in front (occlusion). 3 %: the fox-dark proxy's warp of the noise-free capture (below).
DEPTH_TOLERANCE = 0.03
# Pixels the model does not cover (α below this) keep the view's own light: no depth to warp along.
MIN_ALPHA = 0.5


@dataclass
class WarpSource:
    """One view as a warp reads it: its camera, linear light [H,W,3], expected depth and alpha [H,W]."""
    camera: Camera
    light: Tensor
    depth: Tensor
    alpha: Tensor


def neighbours(cameras: Sequence[Camera], index: int, k: int, min_cos: float = 0.5) -> List[int]:
    """Indices of the ``k`` cameras nearest ``cameras[index]``'s centre among those whose viewing axis lies
    within acos(``min_cos``) of its own (60°: a neighbour facing away sees other surfaces), nearest first."""
    me = cameras[index]
    centre, axis = me.center, me.viewmat[2, :3]
    ranked = []
    for j, cam in enumerate(cameras):
        if j == index or float(cam.viewmat[2, :3] @ axis) <= min_cos:
            continue
        ranked.append((float((cam.center - centre).norm()), j))
    return [j for _, j in sorted(ranked)[:k]]


def _pixel_rays(camera: Camera, device: torch.device) -> Tuple[Tensor, Tensor]:
    """(x/z, y/z) [H,W] float64 of the rays through the pixel centres ((i + 0.5, j + 0.5), Camera's convention)."""
    ys = (torch.arange(camera.height, device=device, dtype=torch.float64) + 0.5 - camera.cy) / camera.fy
    xs = (torch.arange(camera.width, device=device, dtype=torch.float64) + 0.5 - camera.cx) / camera.fx
    return xs[None, :].expand(camera.height, -1), ys[:, None].expand(-1, camera.width)


def warp_average(target: WarpSource, sources: Sequence[WarpSource],
                 tolerance: float = DEPTH_TOLERANCE) -> Tuple[Tensor, Tensor]:
    """(the mean [H,W,3] of ``target``'s light and each source's light warped into it, in ``target.light``'s dtype;
    the count of views averaged [H,W], at least 1). A source pixel counts where the target's point lands inside
    the source, in front of it, on a covered pixel (α ≥ MIN_ALPHA) whose depth agrees within ``tolerance``; target
    pixels without coverage keep their own light alone. Bilinear in the source's light, nearest in its depth."""
    dev = target.light.device
    cam = target.camera
    rx, ry = _pixel_rays(cam, dev)
    z = target.depth.to(dev, torch.float64)
    pts = torch.stack([rx * z, ry * z, z, torch.ones_like(z)], -1)  # camera space, homogeneous
    world = pts @ torch.linalg.inv(cam.viewmat).to(dev).T
    covered = target.alpha.to(dev) >= MIN_ALPHA
    total = target.light.to(torch.float64).clone()
    count = torch.ones(cam.height, cam.width, dtype=torch.float64, device=dev)
    for src in sources:
        sc = src.camera
        p = world @ sc.viewmat.to(dev).T
        zs = p[..., 2]
        zsafe = zs.clamp_min(1e-12)
        u = sc.fx * p[..., 0] / zsafe + sc.cx
        v = sc.fy * p[..., 1] / zsafe + sc.cy
        grid = torch.stack([2.0 * u / sc.width - 1.0, 2.0 * v / sc.height - 1.0], -1)[None].to(src.light.dtype)
        light = F.grid_sample(src.light.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border",
                              align_corners=False)[0].permute(1, 2, 0)
        maps = torch.stack([src.depth, src.alpha]).to(grid.dtype)[None]
        depth, alpha = F.grid_sample(maps, grid, mode="nearest", padding_mode="border", align_corners=False)[0]
        inside = (u >= 0.5) & (u <= sc.width - 0.5) & (v >= 0.5) & (v <= sc.height - 0.5) & (zs > 0)
        keep = covered & inside & (alpha >= MIN_ALPHA) & ((depth.double() - zs).abs() <= tolerance * zs)
        total += torch.where(keep[..., None], light.double(), torch.zeros_like(total))
        count += keep.double()
    return (total / count[..., None]).to(target.light.dtype), count.to(target.light.dtype)
