"""One-off probe (issue 65): the illumination field's training kernels, fp32 FMAs against the tensor cores (TF32,
``model.illumination.tf32``), at a trained scene's Gaussian count, on one GPU.

    python experiments/illum_tc_probe.py [--n 58000 8000] [--repeats 200]

Prints, per N: the GPU time of one forward + backward through the kernels (CUDA events, mean over ``repeats`` after
warm-up), each path's kernels by name from torch.profiler, and the TF32 outputs' and gradients' distance from the
fp32 kernels' (relative norm).
"""
from __future__ import annotations

import argparse
import collections
import copy

import torch

from retinexgs.model.illumination import IlluminationField
from retinexgs.model.illumination_kernel import kernels_apply


def step(field: IlluminationField, means: torch.Tensor, center: torch.Tensor, g: torch.Tensor):
    """One forward + backward: the output and every gradient."""
    params = list(field.parameters())
    out = kernels_apply(field, means, center)
    return [out.detach()] + list(torch.autograd.grad(out, [means] + params, g))


def timed(fn, repeats: int) -> float:
    """Mean GPU time of ``fn`` in µs over ``repeats`` calls (CUDA events, after 10 warm-ups)."""
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


def kernel_times(fn, repeats: int) -> "collections.Counter[str]":
    """Each kernel's GPU time in µs per call (torch.profiler)."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
        for _ in range(repeats):
            fn()
        torch.cuda.synchronize()
    times: "collections.Counter[str]" = collections.Counter()
    for e in prof.events():
        if e.device_type == torch.autograd.DeviceType.CUDA:
            times[e.name[:70]] += e.device_time / repeats
    return times


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, nargs="+", default=[58000, 8000])
    ap.add_argument("--repeats", type=int, default=200)
    args = ap.parse_args()
    torch.manual_seed(0)
    fp32 = IlluminationField().cuda()
    with torch.no_grad():
        fp32.head[-1].weight.normal_(0, 0.5)
    tf32 = copy.deepcopy(fp32)
    tf32.tf32 = True
    center = torch.tensor([0.3, -0.2, 2.5], device="cuda")
    print(torch.cuda.get_device_name(), flush=True)
    for n in args.n:
        means = (torch.randn(n, 3, device="cuda") * 1.5).requires_grad_(True)
        g = torch.randn(n, 3, device="cuda")
        row = {}
        for name, field in (("fp32", fp32), ("tf32", tf32)):
            row[name] = timed(lambda: step(field, means, center, g), args.repeats)
        print(f"N = {n}: forward + backward {row['fp32']:.1f} µs (fp32) -> {row['tf32']:.1f} µs (tf32), "
              f"x{row['tf32'] / row['fp32']:.3f}", flush=True)
        for name, field in (("fp32", fp32), ("tf32", tf32)):
            top = kernel_times(lambda: step(field, means, center, g), 50).most_common(8)
            print(f"  {name}: " + "; ".join(f"{k} {v:.1f}" for k, v in top), flush=True)
        a, b = step(fp32, means, center, g), step(tf32, means, center, g)
        names = ["rgb", "means"] + [k for k, _ in fp32.named_parameters()]
        print("  tf32 vs fp32 (relative norm): " + ", ".join(
            f"{k} {float((y - x).norm() / x.norm().clamp_min(1e-12)):.1e}" for k, x, y in zip(names, a, b)),
            flush=True)


if __name__ == "__main__":
    main()
