"""The demo scene's analytic ray caster, in torch: one implementation for the small demo (CPU, float64) and the
large scale-benchmark scene (GPU, float32). Scene (world units, y up): a 6x6 checkered ground square at y = 0 with a
colour gradient, three textured spheres and a gridded box; a warm directional light with hard shadows, a cool
ambient term and a smooth falloff towards the edges; rays that miss see a dim sky gradient
(:mod:`retinexgs.demo.synthetic` describes the files written from it)."""
from __future__ import annotations

import math
from typing import Tuple, Union

import numpy as np
import torch

from retinexgs.data.srgb import srgb_to_linear

# Scene description (fixed geometry; the seed only moves cameras and draws noise).
GROUND_HALF = 3.0
SPHERES = (  # centre, radius, texture id
    ((-0.65, 0.45, 0.15), 0.45, "stripes"),
    ((0.75, 0.35, -0.35), 0.35, "gradient"),
    ((0.15, 0.25, -1.05), 0.25, "checker"),
)
BOX = ((0.05, 0.0, 0.75), (0.55, 0.6, 1.25))  # min corner, max corner (axis aligned)
LIGHT_DIR = np.array([0.45, 1.0, 0.35]) / np.linalg.norm([0.45, 1.0, 0.35])
LIGHT_RGB = np.array([1.0, 0.93, 0.82]) * 0.95
AMBIENT_RGB = np.array([0.55, 0.62, 0.75]) * 0.35
SCENE_CENTER = np.array([0.0, 0.35, 0.0])
# Object ids returned by cast.
MISS, GROUND, BOX_ID = -1, 0, 100  # spheres are 1, 2, 3


def _vec(x, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, np.float64), dtype=like.dtype, device=like.device)


def _hit_spheres(o: torch.Tensor, d: torch.Tensor, tmin: float = 1e-6) -> Tuple[torch.Tensor, torch.Tensor]:
    inf = torch.full((o.shape[0],), math.inf, dtype=o.dtype, device=o.device)
    t_best, idx = inf.clone(), torch.full((o.shape[0],), -1, dtype=torch.long, device=o.device)
    for s, (c, r, _) in enumerate(SPHERES):
        oc = o - _vec(c, o)
        b = (oc * d).sum(-1)
        disc = b * b - ((oc * oc).sum(-1) - r * r)
        sq = disc.clamp_min(0.0).sqrt()
        t0, t1 = -b - sq, -b + sq
        t = torch.where(t0 > tmin, t0, torch.where(t1 > tmin, t1, inf))
        t = torch.where(disc >= 0, t, inf)
        better = t < t_best
        t_best = torch.where(better, t, t_best)
        idx = torch.where(better, torch.full_like(idx, s), idx)
    return t_best, idx


def _hit_box(o: torch.Tensor, d: torch.Tensor, tmin: float = 1e-6) -> Tuple[torch.Tensor, torch.Tensor]:
    lo, hi = _vec(BOX[0], o), _vec(BOX[1], o)
    inv = 1.0 / torch.where(d == 0, torch.full_like(d, 1e-30), d)
    ta, tb = (lo - o) * inv, (hi - o) * inv
    tnear, tfar = torch.minimum(ta, tb), torch.maximum(ta, tb)
    t0, axis = tnear.max(1)
    t1 = tfar.min(1).values
    hit = (t0 <= t1) & (t0 > tmin)
    return torch.where(hit, t0, torch.full_like(t0, math.inf)), axis


def _hit_ground(o: torch.Tensor, d: torch.Tensor, tmin: float = 1e-6) -> torch.Tensor:
    t = -o[:, 1] / d[:, 1]
    p = o + t[:, None] * d
    ok = (d[:, 1] < 0) & (t > tmin) & (p[:, 0].abs() <= GROUND_HALF) & (p[:, 2].abs() <= GROUND_HALF)
    return torch.where(ok, t, torch.full_like(t, math.inf))


def cast(o: torch.Tensor, d: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Intersect rays (origins ``o`` [N,3], unit directions ``d`` [N,3]) with the scene: (t [N], inf on a miss;
    obj [N]: :data:`MISS`, :data:`GROUND`, spheres 1..3, :data:`BOX_ID`; point [N,3]; normal [N,3])."""
    ts, si = _hit_spheres(o, d)
    tb, axis = _hit_box(o, d)
    tg = _hit_ground(o, d)
    t = torch.minimum(torch.minimum(ts, tb), tg)
    obj = torch.full_like(si, MISS)
    obj = torch.where(torch.isfinite(tg) & (tg == t), torch.full_like(obj, GROUND), obj)
    obj = torch.where(torch.isfinite(tb) & (tb == t), torch.full_like(obj, BOX_ID), obj)
    obj = torch.where(torch.isfinite(ts) & (ts == t), si + 1, obj)
    p = o + torch.where(torch.isfinite(t), t, torch.zeros_like(t))[:, None] * d
    n = torch.zeros_like(p)
    n[obj == GROUND] = _vec((0.0, 1.0, 0.0), p)
    for s, (c, r, _) in enumerate(SPHERES):
        m = obj == s + 1
        n[m] = (p[m] - _vec(c, p)) / r
    m = obj == BOX_ID
    if bool(m.any()):
        ax = axis[m]
        rows = torch.arange(len(ax), device=p.device)
        nb = torch.zeros((len(ax), 3), dtype=p.dtype, device=p.device)
        nb[rows, ax] = -torch.sign(d[m][rows, ax])
        n[m] = nb
    return t, obj, p, n


def albedo(p: torch.Tensor, n: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
    """Procedural sRGB-encoded albedo [N,3] at surface points (0 on a miss)."""
    a = torch.zeros_like(p)
    m = obj == GROUND
    if bool(m.any()):
        q = p[m]
        chk = (torch.floor(q[:, 0] / 0.5) + torch.floor(q[:, 2] / 0.5)) % 2
        u = (q[:, 0] / GROUND_HALF + 1) / 2
        base = torch.stack([0.55 + 0.25 * u, 0.5 - 0.1 * u, 0.35 + 0.2 * (1 - u)], -1)
        a[m] = base * (0.6 + 0.4 * chk)[:, None]
    for s, (c, r, tex) in enumerate(SPHERES):
        m = obj == s + 1
        if not bool(m.any()):
            continue
        q = (p[m] - _vec(c, p)) / r
        lon = torch.atan2(q[:, 2], q[:, 0])
        lat = torch.asin(q[:, 1].clamp(-1, 1))
        if tex == "stripes":
            st = (torch.floor(lon / (math.pi / 6)) % 2)[:, None]
            a[m] = st * _vec([0.85, 0.2, 0.15], p) + (1 - st) * _vec([0.95, 0.85, 0.6], p)
        elif tex == "gradient":
            a[m] = (0.25 + 0.6 * (q * 0.5 + 0.5)[:, [1, 2, 0]]).clamp(0, 1)
        else:
            chk = ((torch.floor(lon / (math.pi / 4)) + torch.floor(lat / (math.pi / 6))) % 2)[:, None]
            a[m] = chk * _vec([0.15, 0.45, 0.8], p) + (1 - chk) * _vec([0.9, 0.9, 0.85], p)
    m = obj == BOX_ID
    if bool(m.any()):
        q = p[m]
        grid = (((((q / 0.1) % 1.0) - 0.5).abs() > 0.4) & (n[m].abs() < 0.5)).any(1)
        a[m] = torch.where(grid[:, None], _vec([0.1, 0.15, 0.1], p), _vec([0.3, 0.7, 0.35], p))
    return a


def rays(cam, ox: float, oy: float, dtype: torch.dtype, device: torch.device) -> Tuple[torch.Tensor, torch.Tensor]:
    """Origins and unit directions [H*W,3] of camera ``cam`` (a :class:`retinexgs.demo.synthetic.DemoCamera`)
    through (col + ox, row + oy) of each pixel: image rows go down (−up), columns right; (0.5, 0.5) is the centre."""
    c2w = torch.as_tensor(cam.c2w_gl, dtype=torch.float64)
    right, up, back = (c2w[:3, k].to(device, dtype) for k in range(3))
    j = torch.arange(cam.width, dtype=dtype, device=device)
    i = torch.arange(cam.height, dtype=dtype, device=device)
    xn = (j[None, :] + ox - cam.cx) / cam.fx
    yn = (i[:, None] + oy - cam.cy) / cam.fy
    d = (-back) + xn[..., None] * right + (-yn[..., None]) * up
    d = (d / d.norm(dim=-1, keepdim=True)).reshape(-1, 3)
    return c2w[:3, 3].to(device, dtype).expand_as(d), d


def render_linear(cam, supersample: int = 2, device: Union[str, torch.device] = "cpu",
                  dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Normal-light linear radiance [H,W,3] of ``cam`` on ``device`` (``supersample``² rays per pixel,
    box-filtered), one supersample offset at a time (about 0.5 KB of working memory per pixel in float32)."""
    device = torch.device(device)
    ss = max(1, int(supersample))
    light, light_rgb, ambient = (torch.as_tensor(v, dtype=dtype, device=device)
                                 for v in (LIGHT_DIR, LIGHT_RGB, AMBIENT_RGB))
    sky_rgb = torch.tensor([0.8, 0.9, 1.2], dtype=dtype, device=device)
    total = torch.zeros((cam.height * cam.width, 3), dtype=dtype, device=device)
    for b in range(ss):
        for a in range(ss):
            o, d = rays(cam, (a + 0.5) / ss, (b + 0.5) / ss, dtype, device)
            _, obj, p, n = cast(o, d)
            colour = srgb_to_linear(albedo(p, n, obj))
            lit = obj != MISS
            ndl = (n @ light).clamp_min(0.0)
            vis = torch.ones_like(ndl)
            if bool(lit.any()):
                pl, nl = p[lit], n[lit]
                so = pl + 1e-4 * nl
                sd = light.expand_as(so)
                shadowed = torch.isfinite(_hit_spheres(so, sd)[0]) | torch.isfinite(_hit_box(so, sd)[0])
                vis[lit] = (~shadowed).to(dtype)
            r2 = p[:, 0] ** 2 + p[:, 2] ** 2
            falloff = 0.55 + 0.45 * torch.exp(-r2 / 4.0)
            irr = (ambient[None] + light_rgb[None] * (ndl * vis)[:, None]) * falloff[:, None]
            sky = (0.06 + 0.10 * d[:, 1].clamp(0, 1))[:, None] * sky_rgb
            total += torch.where(lit[:, None], colour * irr, sky)
    return (total / (ss * ss)).reshape(cam.height, cam.width, 3)
