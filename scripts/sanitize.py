"""Small GPU workloads for compute-sanitizer (memcheck / racecheck) of the CUDA kernels.

    compute-sanitizer --tool memcheck --error-exitcode 9 python scripts/sanitize.py [raster|frame|all]

Targets:

- ``raster``: small forward + backward renders, then the projection's finiteness check on a bad input (its flag
  write and the pinned read-back: a NaN mean must be refused);
- ``frame``: small fused-colour and inference-renderer frames (the shared-memory weight staging, float32 and
  float64, one case reading float64 weights from global memory);
- ``all`` (default): both, in that order.

``scripts/device.sh tests`` runs each target under memcheck and racecheck on the device machine.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

TESTS = Path(__file__).resolve().parents[1] / "tests"


def sanitize_raster() -> None:
    from retinexgs.bench.raster_ours import render_ours
    from retinexgs.demo.splats import orbit_camera, random_scene

    for n, w, h in [(3000, 97, 61), (500, 33, 17)]:
        scene = {k: v.requires_grad_() for k, v in random_scene(n, device="cuda").items()}
        image = render_ours(scene, orbit_camera(w, h), 3)
        image.sum().backward()
    # The projection's finiteness check on a bad input (its flag write and the pinned read-back), then a clean render.
    scene = random_scene(500, device="cuda")
    scene["means"][7, 1] = float("nan")
    try:
        render_ours(scene, orbit_camera(33, 17), 3)
        raise SystemExit("a NaN mean was not refused")
    except ValueError as err:
        print("refused as expected:", str(err)[:60])
    torch.cuda.synchronize()
    print("sanitize raster run finished")


def sanitize_frame() -> None:
    sys.path.insert(0, str(TESTS))
    from scenes import make_camera
    from test_fused_colors import SHAPES, make_field, make_gaussians, make_model

    from retinexgs.model.inference import InferenceRenderer, fused_gaussian_colors

    for dtype in (torch.float32, torch.float64):
        for shape in SHAPES + [(10, 4, 128, 3, 32)]:  # the last one reads float64 weights from global memory
            g, f = make_gaussians(n=333, dtype=dtype).cuda(), make_field(shape, dtype).cuda()
            fused_gaussian_colors(g, [0.3, -0.2, 2.5], 3, f)
        fused_gaussian_colors(g, [0.3, -0.2, 2.5], 3, None)
    model = make_model(n=500).cuda()
    renderer = InferenceRenderer(model, 3)
    cam = make_camera(width=50, height=30, eye=(0.3, -0.2, -3.0))
    for _ in range(3):
        renderer.render(cam, exposure=0.8)
    torch.cuda.synchronize()
    print("sanitize frame run finished")


TARGETS = {"raster": sanitize_raster, "frame": sanitize_frame}


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n".join(__doc__.splitlines()[2:]))
    ap.add_argument("target", nargs="?", default="all", choices=[*TARGETS, "all"])
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("sanitize: no CUDA device", file=sys.stderr)
        return 2
    for name, fn in TARGETS.items():
        if args.target in (name, "all"):
            fn()
    return 0


if __name__ == "__main__":
    sys.exit(main())
