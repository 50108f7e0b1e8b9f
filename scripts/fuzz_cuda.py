"""Fuzz the CUDA rasterizer against the CPU kernels (device machine): degenerate Gaussians and cameras.

    python scripts/fuzz_cuda.py [--cases 300] [--seed 0]

Each case mixes ordinary Gaussians with edge cases (zero / 1e-8 / 1e4 scales, zero and unnormalised
quaternions, opacities 0 and 1, centres behind the camera, on the near plane, far outside the image, a
thousand stacked on one pixel) on images from 1x1 to odd sizes, with 1-64 channels. Checked per case: CUDA
outputs and gradients finite, alpha in [0, 1], colour within the inputs' range, and CUDA equal to the CPU
kernels (image/alpha abs 1e-4 + rel 1e-4; gradients relative to their scale, 1e-3). Prints one summary line
and each failing case; exit 1 on any failure.
"""
from __future__ import annotations

import argparse
import math
import sys
from typing import Dict, List

import torch

sys.path.insert(0, "tests")
from scenes import make_camera  # noqa: E402

from retinexgs.render import rasterize_gaussians  # noqa: E402

EDGES = ["scale0", "scale_tiny", "scale_huge", "quat0", "quat_big", "opacity0", "opacity1", "behind", "near",
         "outside", "stack"]


def make_case(seed: int) -> Dict:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    sizes = [(1, 1), (1, 7), (13, 1), (17, 9), (45, 37), (64, 48), (97, 61)]
    w, h = sizes[int(r(1) * len(sizes))]
    C = [1, 3, 6, 7, 33, 64][int(r(1) * 6)]
    n = int(20 + r(1) * 300)
    means = (r(n, 3) * 2 - 1) * 1.2
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(r(n, 3) * 2 - 3)
    opac = r(n) * 0.9 + 0.05
    colors = r(n, C)
    cam = make_camera(width=w, height=h)
    vm = cam.viewmat
    edges = [e for e in EDGES if r(1) < 0.35]
    k = max(1, n // 10)
    for e in edges:
        idx = torch.randperm(n, generator=g)[:k]
        if e == "scale0":
            scales[idx] = 0.0
        elif e == "scale_tiny":
            scales[idx] = 1e-8
        elif e == "scale_huge":
            scales[idx] = 1e4
        elif e == "quat0":
            quats[idx] = 0.0
        elif e == "quat_big":
            quats[idx] *= 1e6
        elif e == "opacity0":
            opac[idx] = 0.0
        elif e == "opacity1":
            opac[idx] = 1.0
        elif e in ("behind", "near"):
            # camera-space point -> world: x_w = R^T (x_c - t)
            zc = -1.0 if e == "behind" else cam.near
            pc = torch.cat([(r(k, 2) - 0.5) * 0.02, torch.full((k, 1), zc, dtype=torch.float64)], 1)
            means[idx] = (pc - vm[:3, 3]) @ vm[:3, :3]
        elif e == "outside":
            means[idx] = means[idx] + 1e3
        elif e == "stack":
            means[idx] = means[0].clone()
    return dict(means=means, quats=quats, scales=scales, opac=opac, colors=colors, cam=cam, edges=edges, C=C)


def render(case: Dict, device: str):
    args = [case[k].to(device=device, dtype=torch.float32).clone().requires_grad_(True)
            for k in ("means", "quats", "scales", "opac", "colors")]
    out = rasterize_gaussians(*args, case["cam"])
    w = torch.linspace(0.5, 1.5, out.image.numel(), device=device, dtype=torch.float32).reshape(out.image.shape)
    ((out.image * w).sum() + out.alpha.sum()).backward()
    return out.image.detach().cpu(), out.alpha.detach().cpu(), [a.grad.detach().cpu() for a in args]


def check(case: Dict) -> List[str]:
    problems = []
    img_c, a_c, g_c = render(case, "cuda")
    img_h, a_h, g_h = render(case, "cpu")
    if not (torch.isfinite(img_c).all() and torch.isfinite(a_c).all()):
        problems.append("non-finite CUDA output")
    if not all(torch.isfinite(x).all() for x in g_c):
        problems.append("non-finite CUDA gradient")
    if a_c.min() < 0 or a_c.max() > 1 + 1e-6:
        problems.append(f"alpha out of [0,1]: {float(a_c.min())}..{float(a_c.max())}")
    lo, hi = min(0.0, float(case["colors"].min())), float(case["colors"].max())
    if img_c.min() < lo - 1e-5 or img_c.max() > hi + 1e-5:
        problems.append("colour outside the inputs' range")
    for name, x, y in [("image", img_c, img_h), ("alpha", a_c, a_h)]:
        err = float((x - y).abs().max()) if x.numel() else 0.0
        if err > 1e-4 + 1e-4 * float(y.abs().max() if y.numel() else 0):
            problems.append(f"{name} CUDA vs CPU max abs diff {err:.2e}")
    for name, x, y in zip(("means", "quats", "scales", "opacities", "colors"), g_c, g_h):
        scale = float(y.abs().max()) if y.numel() else 0.0
        err = float((x - y).abs().max()) if y.numel() else 0.0
        if err > 1e-3 * max(scale, 1e-3):
            problems.append(f"grad {name} CUDA vs CPU max diff {err:.2e} (scale {scale:.2e})")
    return problems


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=300)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    if not torch.cuda.is_available():
        print("no CUDA device")
        return 2
    failures = 0
    edge_counts = {e: 0 for e in EDGES}
    for i in range(args.cases):
        case = make_case(args.seed * 100003 + i)
        for e in case["edges"]:
            edge_counts[e] += 1
        try:
            problems = check(case)
        except Exception as exc:  # a raised error is a finding too (unless it is a clear ValueError)
            problems = [f"{type(exc).__name__}: {str(exc)[:200]}"]
        if problems:
            failures += 1
            w, h = case["cam"].width, case["cam"].height
            print(f"case {i}: {w}x{h} C={case['C']} N={case['means'].shape[0]} edges={case['edges']}: "
                  + "; ".join(problems))
    print(f"fuzz_cuda: {args.cases} cases, {failures} failing; edge cases used: {edge_counts}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
