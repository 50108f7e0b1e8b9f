"""Bad inputs to the rendering API raise TypeError/ValueError naming the argument; nothing crashes."""
import math

import pytest
import torch

from retinexgs.render import Camera, rasterize_gaussians, spherical_harmonics
from retinexgs.render._backend import kernels
from scenes import make_camera, random_gaussians

NAMES = ("means", "quats", "scales", "opacities", "colors")


def good():
    return list(random_gaussians(5, 3)), make_camera()


@pytest.mark.parametrize("index,bad,error,word", [
    (0, lambda t: t[:, :2], ValueError, "means"),
    (1, lambda t: t[:, :3], ValueError, "quats"),
    (2, lambda t: t[:4], ValueError, "scales"),
    (3, lambda t: t.unsqueeze(-1), ValueError, "opacities"),
    (4, lambda t: t[:, :0], ValueError, "colors"),
    (1, lambda t: t.float(), TypeError, "quats"),
    (0, lambda t: t.to(torch.int64), TypeError, "means"),
    (2, lambda t: t.tolist(), TypeError, "scales"),
    (4, lambda t: torch.empty(t.shape, dtype=t.dtype, device="meta"), ValueError, "colors"),
])
def test_bad_tensor_arguments(index, bad, error, word):
    args, cam = good()
    args[index] = bad(args[index])
    with pytest.raises(error, match=word):
        rasterize_gaussians(*args, cam)


def test_empty_gaussians():
    args, cam = good()
    with pytest.raises(ValueError, match="no Gaussians"):
        rasterize_gaussians(*[a[:0] for a in args], cam)


@pytest.mark.parametrize("field,value,word", [
    ("fx", math.nan, "fx"), ("fy", math.inf, "fy"), ("cx", math.nan, "cx"), ("fx", -3.0, "fx"),
    ("width", 0, "width"), ("height", -5, "height"), ("width", 2.5, "width"), ("near", 0.0, "near"),
])
def test_bad_camera(field, value, word):
    kwargs = dict(viewmat=torch.eye(4), fx=30.0, fy=30.0, cx=10.0, cy=10.0, width=20, height=20)
    kwargs[field] = value
    with pytest.raises(ValueError, match=word):
        Camera(**kwargs)


def test_bad_viewmat():
    with pytest.raises(ValueError, match="viewmat"):
        Camera(torch.eye(3), 30.0, 30.0, 10.0, 10.0, 20, 20)
    vm = torch.eye(4)
    vm[0, 3] = math.nan
    with pytest.raises(ValueError, match="viewmat"):
        Camera(vm, 30.0, 30.0, 10.0, 10.0, 20, 20)


def test_camera_must_be_a_camera():
    args, _ = good()
    with pytest.raises(TypeError, match="camera"):
        rasterize_gaussians(*args, {"fx": 1})


def test_bad_background_and_sh():
    args, cam = good()
    with pytest.raises(ValueError, match="background"):
        rasterize_gaussians(*args, cam, background=torch.zeros(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="degree"):
        spherical_harmonics(4, torch.zeros(2, 3), torch.zeros(2, 16, 3))
    with pytest.raises(ValueError, match="coeffs"):
        spherical_harmonics(2, torch.zeros(2, 3), torch.zeros(2, 4, 3))
    with pytest.raises(ValueError, match="dirs"):
        spherical_harmonics(1, torch.zeros(3, 3), torch.zeros(2, 4, 3))


def test_kernel_library_checks_its_own_arguments():
    # The bindings check too, so a direct caller of retinexgs._C gets an error, not a crash.
    C = kernels()
    m = torch.zeros(3, 3)
    with pytest.raises(ValueError, match="quats"):
        C.project_forward(m, torch.zeros(2, 4), torch.ones(3, 3), torch.ones(3), [0.0] * 16, 1.0, 1.0, 0.0, 0.0,
                          4, 4, 0.01, 100.0)
    with pytest.raises(ValueError, match="fx"):
        C.project_forward(m, torch.zeros(3, 4), torch.ones(3, 3), torch.ones(3), [0.0] * 16, math.nan, 1.0, 0.0,
                          0.0, 4, 4, 0.01, 100.0)
    with pytest.raises(ValueError, match="width"):
        C.bin_gaussians(torch.zeros(3, 2), torch.zeros(3, 2, dtype=torch.int32), torch.zeros(3), 0, 4)
    with pytest.raises(TypeError, match="radii"):
        C.bin_gaussians(torch.zeros(3, 2), torch.zeros(3, 2), torch.zeros(3), 4, 4)
    with pytest.raises(ValueError, match="tile_ranges"):
        C.rasterize_forward(torch.zeros(3, 2), torch.zeros(3, 3), torch.zeros(3, 3), torch.zeros(3),
                            torch.zeros(0, dtype=torch.int32), torch.zeros(5, 2, dtype=torch.int32), 4, 4)
