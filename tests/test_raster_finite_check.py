"""The render call's finiteness check, folded into the projection kernel (rgs::FiniteCheck): its flag is set by a
NaN or an infinity in any element of any checked input, on both devices, and the public render still names the
argument."""
import math

import pytest
import torch

from retinexgs.render import rasterize_gaussians
from retinexgs.render._backend import kernels
from scenes import make_camera, random_gaussians

N, C = 300, 5
INPUTS = ("means", "quats", "scales", "opacities", "colors", "background")


def inputs(dtype, device="cpu"):
    means, quats, scales, opacities, colors = random_gaussians(N, C, seed=3, dtype=dtype)
    background = torch.rand(C, dtype=dtype)
    return {k: v.to(device) for k, v in zip(INPUTS, (means, quats, scales, opacities, colors, background))}


def flag_of(args, check=True, cam=None):
    cam = cam or make_camera(width=64, height=48)
    out = kernels().project_forward(args["means"], args["quats"], args["scales"], args["opacities"],
                                    *cam.kernel_args, check, args["colors"] if check else None,
                                    args["background"] if check else None)
    return out[4]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_clean_inputs_give_a_zero_flag_and_no_check_gives_none(dtype):
    args = inputs(dtype)
    flag = flag_of(args)
    assert flag.dtype == torch.int32 and flag.shape == (1,) and int(flag) == 0
    assert flag_of(args, check=False) is None


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("which", INPUTS)
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_any_bad_element_sets_the_flag(dtype, which, value):
    args = inputs(dtype)
    # Every element position, not one: first, last and a middle one of the flattened tensor.
    count = args[which].numel()
    for pos in sorted({0, count // 2 + 1, count - 1}):
        bad = dict(args)
        bad[which] = args[which].clone()
        bad[which].view(-1)[pos] = value
        assert int(flag_of(bad)) == 1, (which, pos)
        # The projection still culls a Gaussian whose geometry is not finite, and nothing else changes.
        out_bad = kernels().project_forward(bad["means"], bad["quats"], bad["scales"], bad["opacities"],
                                            *make_camera(width=64, height=48).kernel_args)
        out_good = kernels().project_forward(args["means"], args["quats"], args["scales"], args["opacities"],
                                             *make_camera(width=64, height=48).kernel_args)
        if which in ("means", "quats", "scales", "opacities"):
            row = pos // (args[which].numel() // N)
            assert (out_bad[3][row] == 0).all()
            keep = torch.ones(N, dtype=torch.bool)
            keep[row] = False
            assert torch.equal(out_bad[3][keep], out_good[3][keep])


def test_colors_only_with_the_check():
    args = inputs(torch.float32)
    cam = make_camera(width=64, height=48)
    with pytest.raises(ValueError, match="check_finite"):
        kernels().project_forward(args["means"], args["quats"], args["scales"], args["opacities"],
                                  *cam.kernel_args, False, args["colors"], None)
    with pytest.raises(ValueError, match="colors"):
        kernels().project_forward(args["means"], args["quats"], args["scales"], args["opacities"],
                                  *cam.kernel_args, True, args["colors"][:7], None)
    with pytest.raises(ValueError, match="background"):
        kernels().project_forward(args["means"], args["quats"], args["scales"], args["opacities"],
                                  *cam.kernel_args, True, args["colors"], args["background"][:2])


@pytest.mark.parametrize("which", INPUTS)
def test_public_render_names_the_argument(which):
    args = inputs(torch.float32)
    bad = dict(args)
    bad[which] = args[which].clone()
    bad[which].view(-1)[-1] = math.nan
    with pytest.raises(ValueError, match=rf"{which} contains non-finite values"):
        rasterize_gaussians(**bad, camera=make_camera(width=64, height=48))
    # validate=False skips the check: the render goes through (culling the bad Gaussian or passing its colour).
    rasterize_gaussians(**bad, camera=make_camera(width=64, height=48), validate=False)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("which", INPUTS)
def test_cuda_flag_matches_the_cpu(dtype, which):
    # nvcc builds with --use_fast_math: the bit test must still see NaN and inf there.
    args = inputs(dtype)
    assert int(flag_of({k: v.cuda() for k, v in args.items()})) == 0
    for value in (math.nan, math.inf):
        for pos in (0, args[which].numel() - 1):
            bad = dict(args)
            bad[which] = args[which].clone()
            bad[which].view(-1)[pos] = value
            assert int(flag_of(bad)) == 1
            assert int(flag_of({k: v.cuda() for k, v in bad.items()})) == 1, (which, value, pos)
