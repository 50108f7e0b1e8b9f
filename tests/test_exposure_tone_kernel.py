"""The exposure tone's kernel (csrc: exposure_tone, what the CUDA frame graph runs) against its pure-torch twin,
retinexgs.model.tone.tone_map, on the CPU; and its checks. The CUDA launcher is compared with this one in
tests/test_cuda_frame.py."""
import pytest
import torch

from retinexgs.model.tone import exposure_gain, tone_map
from retinexgs.render._backend import kernels


def make_image(h=13, w=11, c=6, dtype=torch.float64, seed=0):
    """R̂ and L̂ over [-0.1, 1.2] (clamping on both sides) with the sRGB curves' thresholds and 0, 1 planted."""
    g = torch.Generator().manual_seed(seed)
    img = (torch.rand(h, w, c, generator=g, dtype=torch.float64) * 1.3 - 0.1).to(dtype)
    img[0, 0, :6] = torch.tensor([0.04045, 0.0031308, 0.0, 1.0, 1.0, 0.5], dtype=dtype)
    img[0, 1, :6] = torch.tensor([1.0, 0.2, 0.04045 ** 0.5, 1.0, 0.0, 0.04045 ** 0.5], dtype=dtype)
    return img


def torch_twin(img, gamma, ref, shoulder=1.0):
    return tone_map(img[..., :3], img[..., 3:6], ref, gamma, "exposure", shoulder=shoulder)[0]


@pytest.mark.parametrize("shoulder", [1.0, 0.5, 0.05])
@pytest.mark.parametrize("gamma", [[1.0], [0.4], [0.3, 0.9, 1.7], [2.0]])
def test_kernel_equals_tone_map_float64(gamma, shoulder):
    img = make_image()
    g = torch.tensor(gamma, dtype=torch.float64)
    ref = torch.tensor(0.35, dtype=torch.float64)
    out = kernels().exposure_tone(img, exposure_gain(ref, g), shoulder)
    torch.testing.assert_close(out, torch_twin(img, g, ref, shoulder), rtol=0, atol=1e-14)
    if shoulder < 1:  # the shoulder moves the highlights, and only them
        plain = kernels().exposure_tone(img, exposure_gain(ref, g))
        moved = (out - plain).abs() > 1e-12
        assert moved.any() and bool((out[moved] < plain[moved]).all())


@pytest.mark.parametrize("shoulder", [1.0, 0.5])
def test_kernel_equals_tone_map_float32_and_extra_channels(shoulder):
    img = make_image(c=7, dtype=torch.float32, seed=3)  # a 7th channel (not read) must not shift the pixels
    g = torch.tensor([0.6], dtype=torch.float32)
    ref = torch.tensor(0.2)
    out = kernels().exposure_tone(img, exposure_gain(ref, g), shoulder)
    torch.testing.assert_close(out, torch_twin(img, g, ref, shoulder), rtol=0, atol=2e-6)
    assert out.shape == (13, 11, 3) and out.dtype == torch.float32


def test_kernel_takes_a_non_contiguous_image_and_keeps_nan():
    img = make_image(h=6, w=10, c=6).transpose(0, 1)  # [10, 6, 6], strided
    img[2, 3, 1] = float("nan")
    k = torch.tensor([5.0], dtype=torch.float64)
    out = kernels().exposure_tone(img, k)
    assert torch.isnan(out[2, 3, 1]) and int(torch.isnan(out).sum()) == 1  # a broken pixel is not painted black
    expect = kernels().exposure_tone(img.contiguous(), k)
    torch.testing.assert_close(out, expect, rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("shoulder", [1.0, 0.5])
@pytest.mark.parametrize("balance", [[1.6, 1.0, 0.6],  # gains
                                     [[0.87, -0.19, -0.04], [0.01, 1.01, -0.01], [0.02, 0.07, 1.75]]])  # temp:4000
@pytest.mark.parametrize("gamma", [[0.4], [0.3, 0.9, 1.7]])
def test_kernel_with_a_white_balance_matrix_equals_the_render_path_float64(balance, gamma, shoulder):
    """gain of 9 entries, W·diag(k) row-major (issue 53: the balanced frame in the frame graph's one kernel):
    the torch path render --white-balance takes, shoulder(W·(k·lin(R̂∘L̂))) then the sRGB curve, to rounding;
    negative light a matrix makes is black, as the torch path clips it."""
    from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear
    from retinexgs.model.tone import highlight_shoulder, white_balance
    img = make_image(seed=5)
    g = torch.tensor(gamma, dtype=torch.float64)
    ref = torch.tensor(0.35, dtype=torch.float64)
    k = exposure_gain(ref, g)
    W = torch.tensor(balance, dtype=torch.float64)
    W = torch.diag(W) if W.dim() == 1 else W
    out = kernels().exposure_tone(img, (W * k.expand(3)[None, :]).reshape(9), shoulder)
    light = white_balance(k * srgb_to_linear(img[..., :3] * img[..., 3:6]), W)
    expect = linear_to_srgb(highlight_shoulder(light, shoulder))
    torch.testing.assert_close(out, expect, rtol=0, atol=1e-14)
    if W.dim() == 2 and bool((W < 0).any()):
        assert bool((light < 0).any()) and float(out.min()) == 0.0


def test_kernel_with_a_diagonal_matrix_equals_per_channel_gains():
    img = make_image(seed=2, dtype=torch.float32)
    k = torch.tensor([2.0, 3.0, 0.5])
    torch.testing.assert_close(kernels().exposure_tone(img, torch.diag(k).reshape(9), 0.5),
                               kernels().exposure_tone(img, k, 0.5), rtol=0, atol=1e-6)


def test_gain_one_gives_back_the_product():
    img = make_image().clamp(0, 1)
    out = kernels().exposure_tone(img, torch.ones(1, dtype=torch.float64))
    # srgb(lin(x)) = x, up to the standard's 3e-8 mismatch between its two pieces at the threshold
    torch.testing.assert_close(out, img[..., :3] * img[..., 3:6], rtol=0, atol=1e-7)


@pytest.mark.parametrize("image, gain, match", [
    (torch.zeros(4, 4, 5), torch.ones(1), "image must be"),
    (torch.zeros(16, 6), torch.ones(1), "image must be"),
    (torch.zeros(4, 4, 6), torch.ones(2), "gain must have 1 or 3"),
    (torch.zeros(4, 4, 6), torch.ones(4), "or 9: a 3x3 matrix"),
    (torch.zeros(4, 4, 6), torch.ones(1, 1), "gain must have 1 dims"),
    (torch.zeros(4, 4, 6), torch.ones(1, dtype=torch.float64), "gain must have dtype"),
    (torch.zeros(4, 4, 6, dtype=torch.int32), torch.ones(1), "image must be float32 or float64"),
])
def test_kernel_names_bad_arguments(image, gain, match):
    with pytest.raises((ValueError, TypeError), match=match):
        kernels().exposure_tone(image, gain)


def test_kernel_names_a_bad_shoulder():
    with pytest.raises(ValueError, match="shoulder"):
        kernels().exposure_tone(torch.zeros(4, 4, 6), torch.ones(1), 0.0)
