"""Random Gaussian scenes and cameras for the tests (built here; no data files)."""
from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest
import torch

from retinexgs.render import Camera


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> torch.Tensor:
    """World-to-camera [4,4] float64 for an OpenCV camera at ``eye`` looking at ``target``."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    if x.norm() < 1e-9:
        x = torch.linalg.cross(z, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ eye
    return vm


def make_camera(width=45, height=37, fov_deg=60.0, eye=(0.3, -0.2, -4.0), target=(0.0, 0.0, 0.0),
                near=0.01, cx_shift=0.0) -> Camera:
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return Camera(look_at(eye, target), f, f * 1.05, width / 2 + cx_shift, height / 2 - 0.7, width, height,
                  near=near)


def random_gaussians(n: int, C: int = 3, seed: int = 0, dtype=torch.float64, spread: float = 1.2,
                     scale_range=(-3.0, -1.0), opacity_range=(0.05, 0.98)):
    """means, quats, scales, opacities, colors for n Gaussians around the origin."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * spread
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    lo, hi = scale_range
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=dtype) * (hi - lo) + lo)
    olo, ohi = opacity_range
    opacities = torch.rand(n, generator=g, dtype=dtype) * (ohi - olo) + olo
    colors = torch.rand(n, C, generator=g, dtype=dtype)
    return means, quats, scales, opacities, colors


# A run trained for 3 steps on a 24×18 demo scene: the prepared input of the CLI and resume tests.
TINY_RUN = ["steps=3", "checkpoint.every=3", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
            "model.max_init_points=300", "decomposer.method=lime", "eval.lpips=false"]


def tiny_trained_run(base, overrides=TINY_RUN, n_train=3, n_test=1, width=24, height=18, n_points=200,
                     baseline_overrides=None):
    """(scene folder, run folder) under ``base``: a tiny demo scene and a run of it trained with ``overrides``
    (default TINY_RUN). With ``baseline_overrides`` a second run, ``base/base``, is trained with them too and
    (scene, run, baseline run) is returned."""
    from retinexgs.demo.synthetic import make_demo_scene
    from retinexgs.train.runner import train_run

    scene = make_demo_scene(base / "scene", n_train=n_train, n_test=n_test, width=width, height=height,
                            n_points=n_points)
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: one thread avoids oversubscription stalls
    try:
        train_run(scene, base / "run", ["demo"], list(overrides), "cpu", progress=False, log=lambda s: None)
        if baseline_overrides is not None:
            train_run(scene, base / "base", ["demo"], list(overrides) + list(baseline_overrides), "cpu",
                      progress=False, log=lambda s: None)
    finally:
        torch.set_num_threads(n)
    if baseline_overrides is not None:
        return scene, base / "run", base / "base"
    return scene, base / "run"


def load_script(name: str):
    """The module of ``scripts/<name>.py`` (the development scripts are not a package)."""
    path = Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def run_cli(argv, capsys):
    """Run ``retinexgs ARGV`` in-process: (exit code, stdout, stderr); a traceback is returned in stderr."""
    import traceback

    from retinexgs.cli import main

    capsys.readouterr()
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    except BaseException:  # noqa: BLE001 - a traceback is what the bad-input tests look for
        captured = capsys.readouterr()
        return -1, captured.out, captured.err + "\nTraceback (escaped main):\n" + traceback.format_exc()
    captured = capsys.readouterr()
    return code, captured.out, captured.err


# The CUDA tests' condition: a GPU and a build with the CUDA kernels (they are skipped on CI's CPU machine).
CUDA = torch.cuda.is_available()
try:
    from retinexgs.render import has_cuda
    CUDA = CUDA and has_cuda()
except ImportError:  # pragma: no cover
    CUDA = False
needs_cuda = pytest.mark.skipif(not CUDA, reason="needs a CUDA GPU and retinexgs built with its CUDA kernels")
