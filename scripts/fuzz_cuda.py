"""Fuzz the CUDA rasterizer against the CPU kernels (device machine), over the shared corpus of
``tests/fuzz_corpus.py`` (the one the CPU hypothesis tests in ``tests/test_fuzz_raster.py`` draw from).

    python scripts/fuzz_cuda.py [--cases 300] [--seed 0] [--max-gaussians 40]
    python scripts/fuzz_cuda.py --dry-run --cases 5     # no GPU: build the cases, run only the CPU side
    python scripts/fuzz_cuda.py --case 1234 --show      # replay one case by its seed, print its recipe

Case ``i`` is ``random_recipe(seed * 1000003 + i)`` (degenerate scales and quaternions, opacities 0 and 1,
centres behind the camera / on the near plane / far outside the image / at the camera, thousands stacked on
one pixel, 1x1 and odd-sized images, backgrounds, depth), in float32, and in about a third of the cases
widened from the corpus' 1-7 channels to 8-64 (the CUDA compositing supports 1-64 channels, depth
included). Checked per case, each recipe run three ways:

* float32 (what training uses): the invariants of ``fuzz_corpus.invariant_problems`` on the CUDA outputs
  and gradients (finite, alpha in [0, 1], colour within the inputs' range, depth within [0, alpha * max
  depth]);
* CUDA == CPU kernels, in float64 and in float32, on the *conditioned* recipe (no Gaussian axis longer than
  its distance to the camera, so at most ~10 px per unit of focal length): image, alpha, depth within abs 1e-4
  + rel 1e-4 (elementwise); the gradients of every input (means, quats, scales, opacities, colors,
  background) of the same random linear loss (``fuzz_corpus.linear_loss``) within 1e-3 of their scale (the
  largest CPU gradient of that input). Why conditioned: a 1e4-long Gaussian by the camera spans millions
  of pixels and its 2D covariance has a condition of 1e12 or more, so the last bit of rounding (the GPU's
  fused multiply-adds, its fast-math exp and division) decides its pixels even in float64: there the two
  devices legitimately differ, and only the invariants are checked.

Where the two devices cull a Gaussian differently (a rounding-level tie of the near plane or the opacity
and extent tests) that is noted, not failed, and the comparison is redone without those Gaussians (radii
must then agree exactly). An exception on either device is a failure.

Prints each failing case (seed, shape, edge cases, problems) and one summary line: cases, failures, culling
notes and how many cases hit each edge case. Exit status 1 on any failure, 2 without a CUDA device (unless
``--dry-run``).
"""
from __future__ import annotations

import argparse
import json
import random
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from fuzz_corpus import (ARG_NAMES, build_case, invariant_problems, random_recipe, render_case)

from retinexgs.render import has_cuda  # noqa: E402

MAX_CUDA_CHANNELS = 64  # depth included
WIDE_CHANNELS = (8, 15, 16, 31, 32, 33, 48, 63, 64)
WIDE_FRACTION = 0.35
SEED_STRIDE = 1000003
FWD_TOL = (1e-4, 1e-4)  # abs, rel
GRAD_TOL = 1e-3         # relative to the scale of the CPU gradient
EDGES = ("scale_zero", "scale_tiny", "scale_huge", "quat_zero", "quat_unnormalised", "opacity_zero",
         "opacity_one", "behind", "near_plane", "outside", "far_outside", "at_camera", "stack", "image_1x1",
         "odd_size", "channels_gt_7", "channels_64", "background", "depth", "random_view")


# ---- cases ------------------------------------------------------------------------------------------------

def case_seed(seed: int, i: int) -> int:
    return seed * SEED_STRIDE + i


def conditioned(r: Dict) -> Dict:
    """The recipe with no Gaussian axis longer than its distance to the camera (see the module docstring)."""
    r = json.loads(json.dumps(r))
    for g in r["gaussians"]:
        # No axis longer than the Gaussian's distance to the camera: at most ~10 px per unit of focal here.
        depth = {"near": r["near"], "at_camera": 1e-3 * r["near"]}.get(g["place"], g["depth"])
        g["scale"] = [min(v, depth) for v in g["scale"]]
    return r


def make_recipe(s: int, max_gaussians: int = 40) -> Dict:
    """The corpus recipe of seed ``s``, in float32, widened to 8-64 channels for some seeds."""
    r = random_recipe(s, max_gaussians=max_gaussians)
    r["dtype"] = "float32"
    rng = random.Random(f"channels-{s}")
    if rng.random() < WIDE_FRACTION:
        C = rng.choice(WIDE_CHANNELS)
        if r["render_depth"]:
            C = min(C, MAX_CUDA_CHANNELS - 1)
        for g in r["gaussians"]:
            g["color"] = [rng.uniform(-1, 2) for _ in range(C)]
        if r["background"] is not None:
            r["background"] = [rng.uniform(-1, 2) for _ in range(C)]
    return r


def edges_of(r: Dict) -> List[str]:
    """The edge cases a recipe contains."""
    gs = r["gaussians"]
    C = len(gs[0]["color"])
    hit = set()
    for g in gs:
        for s in g["scale"]:
            if s == 0.0:
                hit.add("scale_zero")
            elif s <= 1e-8:
                hit.add("scale_tiny")
            elif s >= 1e4:
                hit.add("scale_huge")
        n = sum(q * q for q in g["quat"]) ** 0.5
        if n == 0.0:
            hit.add("quat_zero")
        elif not 1e-3 < n < 1e3:
            hit.add("quat_unnormalised")
        if g["opacity"] == 0.0:
            hit.add("opacity_zero")
        elif g["opacity"] == 1.0:
            hit.add("opacity_one")
        hit.add({"behind": "behind", "near": "near_plane", "outside": "outside", "far_outside": "far_outside",
                 "at_camera": "at_camera"}.get(g["place"], ""))
    if r.get("stack"):
        hit.add("stack")
    if r["width"] == 1 and r["height"] == 1:
        hit.add("image_1x1")
    if r["width"] % 2 or r["height"] % 2:
        hit.add("odd_size")
    if C > 7:
        hit.add("channels_gt_7")
    if C + bool(r["render_depth"]) == MAX_CUDA_CHANNELS:
        hit.add("channels_64")
    if r["background"] is not None:
        hit.add("background")
    if r["render_depth"]:
        hit.add("depth")
    if r["view"]["kind"] == "random":
        hit.add("random_view")
    hit.discard("")
    return [e for e in EDGES if e in hit]


def describe(r: Dict, case: Dict) -> str:
    return (f"{r['width']}x{r['height']} C={case['colors'].shape[1]} N={case['means'].shape[0]} "
            f"depth={bool(r['render_depth'])} bg={r['background'] is not None} view={r['view']['kind']}")


def subset(case: Dict, keep: torch.Tensor) -> Dict:
    """The case without the Gaussians where ``keep`` is False."""
    out = dict(case)
    for k in ARG_NAMES:
        out[k] = case[k][keep.to(case[k].device)]
    return out


# ---- comparison --------------------------------------------------------------------------------------------

def compare(out_gpu, grads_gpu: Dict, out_cpu, grads_cpu: Dict, notes: List[str]) -> List[str]:
    """CUDA vs CPU: forward abs+rel 1e-4 elementwise, gradients 1e-3 of their scale; radii equal (a radius one
    pixel apart, a rounding tie of the extent, is only noted in ``notes``)."""
    problems = []
    rg, rc = out_gpu.radii.cpu().long(), out_cpu.radii.long()
    if rg.shape != rc.shape:
        problems.append(f"radii shape {tuple(rg.shape)} vs {tuple(rc.shape)}")
    elif rg.numel() and not torch.equal(rg, rc):
        d = int((rg - rc).abs().max())
        n = int((rg != rc).any(-1).sum())
        (problems if d > 1 else notes).append(f"radii differ for {n} Gaussians (by up to {d} px)")
    atol, rtol = FWD_TOL
    for name in ("image", "alpha", "depth"):
        a, b = getattr(out_gpu, name), getattr(out_cpu, name)
        if a is None or b is None:
            if (a is None) != (b is None):
                problems.append(f"{name} missing on one device")
            continue
        a, b = a.detach().double().cpu(), b.detach().double()
        if a.shape != b.shape:
            problems.append(f"{name} shape {tuple(a.shape)} vs {tuple(b.shape)}")
            continue
        if not a.numel():
            continue
        excess = (a - b).abs() - (atol + rtol * b.abs())
        if bool((excess > 0).any()) or not bool(torch.isfinite(a).all()):
            i = int(excess.nan_to_num(float("inf")).argmax())
            problems.append(f"{name} CUDA vs CPU: max abs diff {float((a - b).abs().max()):.3e} "
                            f"(at flat index {i}: {float(a.reshape(-1)[i]):.6g} vs {float(b.reshape(-1)[i]):.6g})")
    for name, gc in grads_cpu.items():
        gg = grads_gpu.get(name)
        if gg is None:
            problems.append(f"grad {name} missing on CUDA")
            continue
        gg, gc = gg.double().cpu(), gc.double()
        if not gc.numel():
            continue
        scale = float(gc.abs().max())
        err = float((gg - gc).abs().max()) if bool(torch.isfinite(gg).all()) else float("inf")
        if err > GRAD_TOL * max(scale, 1e-6):
            i = int((gg - gc).abs().nan_to_num(float("inf")).argmax())
            problems.append(f"grad {name} CUDA vs CPU: max diff {err:.3e}, scale {scale:.3e} "
                            f"(at flat index {i}: {float(gg.reshape(-1)[i]):.6g} vs {float(gc.reshape(-1)[i]):.6g})")
    return problems


def check_case(r: Dict, s: int, dry_run: bool) -> Tuple[List[str], List[str], str]:
    """(problems, notes, description) of one recipe: float32 invariants on CUDA, then CUDA vs CPU in float64
    and in float32 on the conditioned recipe. ``dry_run``: the CPU side only (render, invariants)."""
    problems, notes, desc = check_one(r, s, dry_run, compare_devices=False)
    if dry_run:
        return problems, notes, desc
    for label, rr in (("float64 conditioned", dict(conditioned(r), dtype="float64")),
                      ("float32 conditioned", conditioned(r))):
        p, n, _ = check_one(rr, s, dry_run, compare_devices=True)
        problems += [f"[{label}] {x}" for x in p]
        notes += [f"[{label}] {x}" for x in n]
    return problems, notes, desc


def check_one(r: Dict, s: int, dry_run: bool, compare_devices: bool) -> Tuple[List[str], List[str], str]:
    """One run of a recipe: invariants on the CUDA outputs, and CUDA vs CPU when ``compare_devices``."""
    notes: List[str] = []
    case_cpu = build_case(r, "cpu")
    desc = describe(r, case_cpu)
    try:
        out_cpu, grads_cpu = render_case(case_cpu, s)
    except Exception as exc:  # noqa: BLE001 - any exception is a finding
        return [f"CPU raised {type(exc).__name__}: {str(exc)[:300]}"], notes, desc
    if dry_run:
        return [f"CPU {p}" for p in invariant_problems(case_cpu, out_cpu, grads_cpu)], notes, desc
    try:
        case_gpu = build_case(r, "cuda")
        out_gpu, grads_gpu = render_case(case_gpu, s)
        torch.cuda.synchronize()
    except Exception as exc:  # noqa: BLE001
        return [f"CUDA raised {type(exc).__name__}: {str(exc)[:300]}"], notes, desc
    problems = [f"CUDA {p}" for p in invariant_problems(case_gpu, out_gpu, grads_gpu)]
    if not compare_devices:
        return problems, notes, desc
    vis_gpu, vis_cpu = out_gpu.visible.cpu(), out_cpu.visible
    flips = vis_gpu != vis_cpu
    if bool(flips.any()):
        # A rounding-level tie of a culling test decided differently: note it, compare the rest.
        notes.append(f"culling differs for {int(flips.sum())} of {flips.numel()} Gaussians")
        keep = ~flips
        if not bool(keep.any()):  # nothing left to compare (the renderer refuses N = 0)
            return problems, notes, desc
        try:
            out_cpu, grads_cpu = render_case(subset(case_cpu, keep), s)
            out_gpu, grads_gpu = render_case(subset(case_gpu, keep), s)
            torch.cuda.synchronize()
        except Exception as exc:  # noqa: BLE001
            return problems + [f"re-render without the flipped Gaussians raised {type(exc).__name__}: "
                               f"{str(exc)[:300]}"], notes, desc
    if out_gpu.num_pairs != out_cpu.num_pairs:
        notes.append(f"tile pairs {out_gpu.num_pairs} (CUDA) vs {out_cpu.num_pairs} (CPU)")
    problems += compare(out_gpu, grads_gpu, out_cpu, grads_cpu, notes)
    return problems, notes, desc


# ---- main --------------------------------------------------------------------------------------------------

def run(cases: int, seed: int = 0, dry_run: bool = False, max_gaussians: int = 40, only: Optional[int] = None,
        show: bool = False, out=print) -> int:
    """Run the fuzz; returns the exit status (0 all held, 1 failures, 2 no CUDA device)."""
    if not dry_run and not (torch.cuda.is_available() and has_cuda()):
        out("fuzz_cuda: no CUDA device (or retinexgs built without its CUDA kernels); use --dry-run for the "
            "CPU side")
        return 2
    seeds = [only] if only is not None else [case_seed(seed, i) for i in range(cases)]
    failures = 0
    edge_counts: Counter = Counter()
    noted = 0
    t0 = time.time()
    for s in seeds:
        r = make_recipe(s, max_gaussians)
        edges = edges_of(r)
        edge_counts.update(edges)
        if show:
            out(json.dumps(r))
        problems, notes, desc = check_case(r, s, dry_run)
        noted += bool(notes)
        if problems:
            failures += 1
            out(f"FAIL case seed {s}: {desc} edges={','.join(edges)}: " + "; ".join(problems)
                + (f" [notes: {'; '.join(notes)}]" if notes else ""))
        elif show and notes:
            out(f"note case seed {s}: {'; '.join(notes)}")
    mode = "dry run (CPU only)" if dry_run else "CUDA: float32 invariants; CUDA vs CPU on conditioned recipes"
    hit = ", ".join(f"{e} {edge_counts[e]}" for e in EDGES)
    out(f"fuzz_cuda [{mode}]: {len(seeds)} cases, {failures} failing, {noted} with culling/radius/pair notes, "
        f"{time.time() - t0:.0f} s; edge cases hit (cases): {hit}")
    if failures:
        out(f"replay one: python scripts/fuzz_cuda.py --case SEED --show{' --dry-run' if dry_run else ''}")
    return 1 if failures else 0


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=300)
    p.add_argument("--seed", type=int, default=0, help="case i uses the corpus seed SEED*1000003+i")
    p.add_argument("--max-gaussians", type=int, default=40, help="per recipe, besides any stack (default 40)")
    p.add_argument("--case", type=int, default=None, metavar="SEED", help="run only the case of this corpus seed")
    p.add_argument("--show", action="store_true", help="print each recipe (JSON) and the notes")
    p.add_argument("--dry-run", action="store_true", help="no GPU: build the cases and check only the CPU side")
    a = p.parse_args(argv)
    return run(a.cases, a.seed, a.dry_run, a.max_gaussians, a.case, a.show)


if __name__ == "__main__":
    sys.exit(main())
