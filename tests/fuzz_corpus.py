"""The fuzz corpus of the rasterizer, shared by ``tests/test_fuzz_raster.py`` (hypothesis, CPU) and
``scripts/fuzz_cuda.py`` (seeded, CUDA vs CPU on the device).

A *recipe* is a plain dict of choices (image size, camera, and per Gaussian: where it sits, its scale,
quaternion, opacity and colour). :func:`build_case` turns a recipe into tensors; :func:`random_recipe` draws
one from a seed without hypothesis (the device machine may not have it); ``tests/test_fuzz_raster.py`` draws
recipes with hypothesis strategies, so failures shrink to small recipes.

Edge cases the corpus mixes in: zero, tiny (1e-8) and huge (1e4) scales; zero and non-normalised
quaternions (norms 1e-6 .. 1e6); opacities 0 and 1; centres behind the camera, exactly on the near plane
and far outside the image; up to thousands of Gaussians stacked on one pixel; images of 1x1 and odd sizes;
principal points off-centre; 1..7 channels, a background or none, a depth channel or none.
"""
from __future__ import annotations

import random
from typing import Dict, List, Optional

import torch

from retinexgs.render import Camera

# Where a Gaussian sits, in camera space.
PLACES = ("front", "behind", "near", "outside", "far_outside", "at_camera")
# Scale and quaternion kinds.
SCALE_SPECIAL = (0.0, 1e-8, 1e4)
SIZES = (1, 2, 3, 5, 7, 15, 16, 17, 31, 33)
NEARS = (0.01, 0.2, 1.0)
# Camera rotations that are exact in floating point (signed permutations, det +1), so the reference and the
# kernels compute the very same camera-space depth (no near-plane ties decided differently by rounding).
EXACT_ROTATIONS = (
    ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    ((-1, 0, 0), (0, -1, 0), (0, 0, 1)),
    ((0, 1, 0), (-1, 0, 0), (0, 0, 1)),
    ((0, 0, 1), (1, 0, 0), (0, 1, 0)),
    ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
)


def quat_matrix(q) -> torch.Tensor:
    """Rotation matrix of a (w, x, y, z) quaternion, float64 (identity for a zero one)."""
    q = torch.as_tensor(q, dtype=torch.float64)
    n = float(q.norm())
    if n < 1e-12:
        return torch.eye(3, dtype=torch.float64)
    w, x, y, z = (q / n).tolist()
    return torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=torch.float64)


def build_camera(r: Dict) -> Camera:
    """The camera of a recipe."""
    w, h = r["width"], r["height"]
    f = r["focal"] * max(w, h)
    vm = torch.eye(4, dtype=torch.float64)
    view = r["view"]
    if view["kind"] == "exact":
        vm[:3, :3] = torch.tensor(EXACT_ROTATIONS[view["index"]], dtype=torch.float64)
        vm[:3, 3] = torch.tensor(view["t"], dtype=torch.float64)
    elif view["kind"] == "random":
        vm[:3, :3] = quat_matrix(view["q"])
        vm[:3, 3] = torch.tensor(view["t"], dtype=torch.float64)
    return Camera(vm, f, f * r["aspect"], w * r["cx"], h * r["cy"], w, h, near=r["near"])


def _camera_point(g: Dict, cam: Camera) -> List[float]:
    """Camera-space centre of one Gaussian of a recipe."""
    place, (u, v) = g["place"], g["uv"]
    z = {"front": g["depth"], "behind": -g["depth"], "near": cam.near, "outside": g["depth"],
         "far_outside": g["depth"], "at_camera": 0.0}[place]
    if place == "outside":  # just beyond the image border (past the guard band for large u, v)
        u, v = u * 4.0, v * 4.0
    elif place == "far_outside":
        u, v = u * 1e6, v * 1e6
    px, py = cam.cx + u * cam.width, cam.cy + v * cam.height  # pixel position for u, v in [-0.5, 0.5]
    if place in ("behind", "at_camera"):
        return [u * 0.5, v * 0.5, z]
    return [(px - cam.cx) / cam.fx * z, (py - cam.cy) / cam.fy * z, z]


def build_case(r: Dict, device: str = "cpu") -> Dict:
    """Tensors of a recipe: means, quats, scales, opacities, colors, camera, background, render_depth."""
    dtype = torch.float64 if r["dtype"] == "float64" else torch.float32
    cam = build_camera(r)
    R, t = cam.viewmat[:3, :3], cam.viewmat[:3, 3]
    gs = r["gaussians"]
    pc = torch.tensor([_camera_point(g, cam) for g in gs], dtype=torch.float64)
    means = (pc - t) @ R  # world = Rᵀ (p - t); exact for the exact rotations with t = 0
    quats = torch.tensor([g["quat"] for g in gs], dtype=torch.float64)
    scales = torch.tensor([g["scale"] for g in gs], dtype=torch.float64)
    opac = torch.tensor([g["opacity"] for g in gs], dtype=torch.float64)
    colors = torch.tensor([g["color"] for g in gs], dtype=torch.float64)
    stack = r.get("stack")
    if stack:  # many Gaussians on one pixel centre, random shapes, seeded
        gen = torch.Generator().manual_seed(stack["seed"])
        n = stack["count"]
        px, py = stack["pixel"]
        z = stack["depth"] + torch.rand(n, generator=gen, dtype=torch.float64) * stack["depth_spread"]
        x = (min(px, cam.width - 1) + 0.5 - cam.cx) / cam.fx * z
        y = (min(py, cam.height - 1) + 0.5 - cam.cy) / cam.fy * z
        spc = torch.stack([x, y, z], -1)
        means = torch.cat([means, (spc - t) @ R])
        quats = torch.cat([quats, torch.randn(n, 4, generator=gen, dtype=torch.float64)])
        scales = torch.cat([scales, stack["scale"] * torch.exp(torch.randn(n, 3, generator=gen, dtype=torch.float64))])
        o = torch.rand(n, generator=gen, dtype=torch.float64)
        o = torch.where(o < 0.3, torch.ones_like(o), o)  # many fully opaque
        opac = torch.cat([opac, o])
        colors = torch.cat([colors, torch.rand(n, colors.shape[1], generator=gen, dtype=torch.float64) * 2 - 0.5])
    bg = r.get("background")
    to = dict(dtype=dtype, device=device)
    return dict(means=means.to(**to), quats=quats.to(**to), scales=scales.to(**to), opacities=opac.to(**to),
                colors=colors.to(**to), camera=cam,
                background=None if bg is None else torch.tensor(bg, dtype=torch.float64).to(**to),
                render_depth=bool(r.get("render_depth")))


ARG_NAMES = ("means", "quats", "scales", "opacities", "colors")


def render_case(case: Dict, seed: int = 0, grads: bool = True):
    """Render a case (gradients on every input) and backpropagate a random linear loss of image, alpha and
    depth. Returns (output, {name: grad}); the inputs are cloned, ``case`` is left untouched."""
    from retinexgs.render import rasterize_gaussians

    args = [case[k].detach().clone().requires_grad_(grads) for k in ARG_NAMES]
    bg = case["background"]
    if bg is not None:
        bg = bg.detach().clone().requires_grad_(grads)
    out = rasterize_gaussians(*args, case["camera"], background=bg, render_depth=case["render_depth"])
    if not grads:
        return out, {}
    loss = linear_loss(out, seed)
    names = list(ARG_NAMES) + (["background"] if bg is not None else [])
    got = torch.autograd.grad(loss, args + ([bg] if bg is not None else []), allow_unused=True)
    return out, {n: (torch.zeros_like(a) if g is None else g) for n, g, a in zip(names, got, args + [bg])}


def linear_loss(out, seed: int):
    """Σ wᵢ·imageᵢ + Σ vᵢ·alphaᵢ (+ Σ uᵢ·depthᵢ), weights drawn on the CPU from ``seed``."""
    gen = torch.Generator().manual_seed(seed)

    def w(x):
        return torch.randn(x.shape, generator=gen, dtype=torch.float64).to(x)

    loss = (out.image * w(out.image)).sum() + (out.alpha * w(out.alpha)).sum()
    if out.depth is not None:
        loss = loss + (out.depth * w(out.depth)).sum()
    return loss


def invariant_problems(case: Dict, out, grads: Dict) -> List[str]:
    """The properties every render must have, as a list of violations (empty = all held):
    outputs finite, alpha in [0, 1], colour inside the per-channel range of the colours and the background
    (0 when there is none), depth in [0, alpha·max visible depth], gradients finite."""
    problems = []
    f32 = case["means"].dtype == torch.float32
    img, alpha = out.image.detach().double().cpu(), out.alpha.detach().double().cpu()
    if not torch.isfinite(img).all():
        problems.append("non-finite image")
    if not torch.isfinite(alpha).all():
        problems.append("non-finite alpha")
    elif alpha.numel() and (alpha.min() < 0 or alpha.max() > 1):
        problems.append(f"alpha outside [0, 1]: {float(alpha.min())} .. {float(alpha.max())}")
    colors = case["colors"].double().cpu()
    bg = case["background"]
    edge = bg.double().cpu() if bg is not None else torch.zeros(colors.shape[1], dtype=torch.float64)
    lo = torch.minimum(colors.min(0).values, edge)
    hi = torch.maximum(colors.max(0).values, edge)
    tol = (1e-4 if f32 else 1e-10) * (1 + torch.maximum(lo.abs(), hi.abs()))
    if torch.isfinite(img).all() and ((img < lo - tol).any() or (img > hi + tol).any()):
        problems.append(f"colour outside the inputs' range: image {img.amin((0, 1)).tolist()} .. "
                        f"{img.amax((0, 1)).tolist()}, inputs {lo.tolist()} .. {hi.tolist()}")
    if out.depth is not None:
        depth = out.depth.detach().double().cpu()
        visible = out.visible.cpu()
        zmax = 0.0
        if visible.any():
            cam = case["camera"]
            R, t = cam.viewmat[:3, :3], cam.viewmat[:3, 3]
            zmax = float((case["means"].double().cpu()[visible] @ R.T + t)[:, 2].max())
        if not torch.isfinite(depth).all():
            problems.append("non-finite depth")
        elif (depth < -1e-12).any() or (depth > alpha * zmax * (1 + (1e-4 if f32 else 1e-9)) + 1e-9).any():
            problems.append(f"depth outside [0, alpha * {zmax}]")
    for name, g in grads.items():
        if not torch.isfinite(g).all():
            problems.append(f"non-finite gradient of {name}")
    if out.means2d.grad is not None and not torch.isfinite(out.means2d.grad).all():
        problems.append("non-finite means2d.grad")
    return problems


# ---- seeded recipes (no hypothesis) ---------------------------------------------------------------------

def random_gaussian_recipe(rng: random.Random, C: int, place: Optional[str] = None) -> Dict:
    """One Gaussian of a recipe, edge cases mixed in with ordinary ones."""
    def scale():
        return rng.choice(SCALE_SPECIAL) if rng.random() < 0.25 else 10 ** rng.uniform(-3, 0.5)

    kind = rng.random()
    if kind < 0.1:
        quat = [0.0, 0.0, 0.0, 0.0]
    else:
        quat = [rng.gauss(0, 1) for _ in range(4)]
        if kind < 0.35:
            m = 10 ** rng.uniform(-6, 6)
            quat = [q * m for q in quat]
    op = rng.random()
    opacity = 0.0 if op < 0.1 else 1.0 if op < 0.25 else rng.random()
    return dict(place=place or rng.choice(PLACES + ("front",) * 6),
                uv=(rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6)), depth=10 ** rng.uniform(-1.5, 1.5),
                scale=[scale() for _ in range(3)], quat=quat, opacity=opacity,
                color=[rng.uniform(-1, 2) for _ in range(C)])


def random_recipe(seed: int, max_gaussians: int = 40, stack_prob: float = 0.15) -> Dict:
    """A whole recipe from a seed (what scripts/fuzz_cuda.py runs)."""
    rng = random.Random(seed)
    C = rng.choice((1, 2, 3, 3, 4, 6, 7))
    view_kind = rng.choice(("identity", "exact", "random"))
    view = {"kind": view_kind, "index": rng.randrange(len(EXACT_ROTATIONS)),
            "q": [rng.gauss(0, 1) for _ in range(4)],
            "t": [rng.uniform(-0.5, 0.5) for _ in range(3)] if view_kind == "random" else [0.0, 0.0, 0.0]}
    r = dict(dtype=rng.choice(("float32", "float64")), width=rng.choice(SIZES), height=rng.choice(SIZES),
             focal=10 ** rng.uniform(-0.5, 1), aspect=rng.uniform(0.8, 1.25), cx=rng.uniform(0.2, 0.8),
             cy=rng.uniform(0.2, 0.8), near=rng.choice(NEARS), view=view,
             background=[rng.uniform(-1, 2) for _ in range(C)] if rng.random() < 0.5 else None,
             render_depth=rng.random() < 0.5,
             gaussians=[random_gaussian_recipe(rng, C) for _ in range(rng.randint(1, max_gaussians))])
    if rng.random() < stack_prob:
        r["stack"] = dict(count=rng.randint(200, 3000), seed=rng.randrange(2**31),
                          pixel=(rng.randrange(r["width"]), rng.randrange(r["height"])),
                          depth=10 ** rng.uniform(-1, 1), depth_spread=rng.choice((0.0, 1.0)),
                          scale=10 ** rng.uniform(-3, -1))
    return r
