"""The scene's near plane (``model.near_fraction``): how close to a camera a Gaussian may be drawn.

Why: a Gaussian that the training views saw as a speck in front of the far content (fitting one view's noise)
covers the whole frame of a camera that passes through it. A novel view on the capture's path does (the test
views of castlep30-dark at 1000 e⁻: 15–69 % of a veiled view's compositing weight came from Gaussians within a
tenth of the scene's depth of its camera; experiments/notes/2026-11-28-near-plane.md). Drawing nothing closer than
a fraction of the nearest content the training views saw removes them, and nothing the views saw. 3DGS's own
renderer culls at a fixed depth of 0.2 scene units; here the depth follows the scene.
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import torch
from torch import Tensor

from retinexgs.render import Camera

# Each view's "nearest content": this quantile of the depths of the initial points inside its frame (the nearest
# few per cent, not the nearest point: a stray SfM point in front of a camera would set the plane by itself).
CONTENT_QUANTILE = 0.05
MIN_POINTS = 8  # a view that sees fewer initial points says nothing about the scene's depth
MAX_POINTS, MAX_CAMERAS = 200_000, 256  # evenly spaced subsets beyond these: a statistic, bounded set-up time


def content_depth(points: Tensor, cameras: Sequence[Camera], quantile: float = CONTENT_QUANTILE) -> float:
    """The training views' nearest content depth: per camera, ``quantile`` of the camera-space depths of the
    ``points`` [P,3] that project inside its frame in front of it; the median over the cameras that see at least
    ``MIN_POINTS`` of them. 0.0 when none does (no near plane can be derived)."""
    pts = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3)
    pts = pts[:: -(-pts.shape[0] // MAX_POINTS) or 1]
    cameras = list(cameras)[:: -(-len(cameras) // MAX_CAMERAS) or 1]
    per_view = []
    for cam in cameras:
        pc = pts @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        z = pc[:, 2]
        front = z > 0
        zs = z.clamp_min(1e-12)
        u = cam.fx * pc[:, 0] / zs + cam.cx
        v = cam.fy * pc[:, 1] / zs + cam.cy
        inside = front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        if int(inside.sum()) >= MIN_POINTS:
            per_view.append(torch.quantile(z[inside], quantile))
    if not per_view:
        return 0.0
    return float(torch.stack(per_view).median())


def with_near(camera: Camera, near: float) -> Camera:
    """``camera`` with its near plane raised to ``near`` (the same camera where it is already at least that)."""
    if near <= camera.near or near >= camera.far:
        return camera
    return dataclasses.replace(camera, near=near)
