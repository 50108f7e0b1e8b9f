"""One-off probe (issue 65): where the illumination MLP's forward + backward spends its GPU time at a trained
scene's Gaussian count, and whether a bias gradient as a matrix-vector product beats torch's column sum.

    python experiments/mlp_kernel_probe.py [--n 58000 8000] [--repeats 200]

Prints, per N: the kernels of one forward + backward of IlluminationField (its own GPU time, by kernel name,
from torch.profiler over ``repeats`` iterations), the whole iteration's time with and without TF32 matmuls, and
g.sum(0) against torch.mv(g.t(), ones) for g [N, 64] / [N, 32] / [N, 3].
"""
from __future__ import annotations

import argparse
import collections

import torch

from retinexgs.model.illumination import IlluminationField


def timed(fn, repeats: int) -> float:
    """Median-free mean GPU time of ``fn`` in µs over ``repeats`` calls (CUDA events, after 10 warm-ups)."""
    for _ in range(10):
        fn()
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    torch.cuda.synchronize()
    start.record()
    for _ in range(repeats):
        fn()
    end.record()
    torch.cuda.synchronize()
    return start.elapsed_time(end) * 1000.0 / repeats


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, nargs="+", default=[58000, 8000])
    ap.add_argument("--repeats", type=int, default=200)
    args = ap.parse_args()
    dev = "cuda"
    field = IlluminationField().to(dev)
    for n in args.n:
        g = torch.Generator(device=dev).manual_seed(0)
        xyz = torch.randn(n, 3, device=dev, generator=g).requires_grad_(True)
        dirs = torch.randn(n, 3, device=dev, generator=g)
        grad = torch.randn(n, 3, device=dev, generator=g)

        def step():
            out = field(xyz, dirs)
            torch.autograd.grad(out, [xyz] + list(field.parameters()), grad)

        for tf32 in (False, True):
            torch.backends.cuda.matmul.allow_tf32 = tf32
            print(f"N={n} forward+backward, tf32={tf32}: {timed(step, args.repeats):.1f} µs")
        torch.backends.cuda.matmul.allow_tf32 = False
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
            for _ in range(args.repeats):
                step()
            torch.cuda.synchronize()
        own = collections.Counter()
        calls = collections.Counter()
        for e in prof.events():
            if e.device_type == torch.autograd.DeviceType.CUDA:
                own[e.name[:90]] += e.device_time_total if hasattr(e, "device_time_total") else e.cuda_time_total
                calls[e.name[:90]] += 1
        total = sum(own.values()) / args.repeats
        print(f"N={n} kernels a forward+backward: {sum(calls.values()) / args.repeats:.0f}, {total:.1f} µs")
        for name, t in own.most_common(25):
            print(f"  {t / args.repeats:8.1f} µs  {calls[name] / args.repeats:4.1f}×  {name}")
        for width in (64, 32, 3):
            m = torch.randn(n, width, device=dev, generator=g)
            ones = torch.ones(n, device=dev)
            a = timed(lambda: m.sum(0), args.repeats)
            b = timed(lambda: torch.mv(m.t(), ones), args.repeats)
            c = timed(lambda: ones[None] @ m, args.repeats)
            err = (m.sum(0) - torch.mv(m.t(), ones)).abs().max().item()
            print(f"N={n} [N,{width}] bias gradient: sum(0) {a:.1f} µs, mv {b:.1f} µs, ones@g {c:.1f} µs "
                  f"(max difference {err:.2e})")


if __name__ == "__main__":
    main()
