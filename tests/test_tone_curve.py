"""The fused tone curve (retinexgs/model/tones/fused_curve.py, csrc/include/rgs/tone_curve.h): the kernel against
its pure-torch twin, values and gradients in float64, its own finite differences, the layouts of the gain and the
callers that now run through it (the exposure tone, the exposed photo, a raw view's linear light)."""
import itertools

import pytest
import torch

from retinexgs.data.srgb import linear_to_srgb, linear_to_srgb_extended, srgb_to_linear, srgb_to_linear_extended
from retinexgs.model.tones.curves import highlight_shoulder
from retinexgs.model.tones.exposure import ExposureTone, exposure_gain
from retinexgs.model.tones.fused_curve import (_ToneCurve, tone_curve, tone_curve_kernel, tone_curve_reference,
                                               to_linear)
from retinexgs.train.losses import exposed

FORMS_IN = ["clip", "open", "extended"]
FORMS_OUT = ["clip", "open", "extended", "linear"]


def values(shape, dtype=torch.float64, seed=0):
    """sRGB-encoded values over [-0.3, 1.6]: negatives (a raw view's noise), the two curves' knees, white and past."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=dtype) * 1.9 - 0.3
    flat = x.view(-1)
    specials = torch.tensor([0.0, 0.04045, 0.0031308, 1.0, -0.01, 0.5], dtype=dtype)
    flat[:specials.numel()] = specials[:flat.numel()]
    return x


def grads(fn, x, gain, seed=1):
    x = x.clone().requires_grad_(True)
    gain = gain.clone().requires_grad_(True)
    y = fn(x, gain)
    w = torch.rand(y.shape, generator=torch.Generator().manual_seed(seed), dtype=y.dtype).to(y.device)
    gx, gg = torch.autograd.grad((y * w).sum(), (x, gain))
    return y.detach(), gx, gg


@pytest.mark.parametrize("form_in,form_out", list(itertools.product(FORMS_IN, FORMS_OUT)))
@pytest.mark.parametrize("knee", [1.0, 0.8])
@pytest.mark.parametrize("layout", ["scalar", "last", "bchw"])
def test_kernel_matches_twin_float64(form_in, form_out, knee, layout):
    if layout == "last":
        x, gain = values((7, 9, 3)), torch.tensor([3.0, 7.5, 0.6], dtype=torch.float64)
    elif layout == "bchw":
        x, gain = values((2, 3, 5, 4)), torch.tensor([2.0, 11.0, 0.9], dtype=torch.float64).view(1, 3, 1, 1)
    else:
        x, gain = values((4, 3, 6, 5)), torch.tensor(5.5, dtype=torch.float64)
    fused = grads(lambda a, k: tone_curve_kernel(a, k, knee, form_in, form_out), x, gain)
    twin = grads(lambda a, k: tone_curve_reference(a, k, knee, form_in, form_out), x, gain)
    for a, b in zip(fused, twin):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_the_kernel_ran_not_the_twin(monkeypatch):
    """The layouts above are the fused path's: a fallback to the twin would make the comparison vacuous."""
    calls = []
    real = _ToneCurve.apply
    monkeypatch.setattr(_ToneCurve, "apply", lambda *a: calls.append(a) or real(*a))
    tone_curve_kernel(values((4, 4, 3)), torch.ones(3, dtype=torch.float64))
    tone_curve_kernel(values((1, 3, 4, 4)), torch.ones(1, 3, 1, 1, dtype=torch.float64))
    tone_curve_kernel(values((1, 3, 4, 4)), torch.ones((), dtype=torch.float64))
    assert len(calls) == 3 and [c[-2:] for c in calls] == [(3, 1), (3, 16), (1, 1)]


@pytest.mark.parametrize("form_in,form_out", [("clip", "clip"), ("open", "open"), ("extended", "extended"),
                                              ("open", "linear"), ("extended", "linear")])
@pytest.mark.parametrize("knee", [1.0, 0.7])
def test_finite_differences_float64(form_in, form_out, knee):
    # away from the clips and the knees (where the curve has kinks), on each side of the sRGB curve's knee
    g = torch.Generator().manual_seed(4)
    x = (torch.rand(3, 4, 3, generator=g, dtype=torch.float64) * 0.3 + 0.05)
    x[0] = x[0] * 0.1 + 0.005  # the linear segment (below 0.04045)
    if form_in == "extended":
        x[1, 0] = -x[1, 0] * 0.2  # a raw view's negative values
    gain = torch.tensor([1.5, 2.0, 2.5], dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda a, k: tone_curve_kernel(a, k, knee, form_in, form_out),
                             (x.requires_grad_(True), gain), eps=1e-7, atol=1e-7)


def test_float32_close_to_twin():
    x = values((64, 48, 3), torch.float32)
    gain = torch.tensor([4.0, 9.0, 1.3])
    for form in FORMS_IN:
        fused = grads(lambda a, k: tone_curve_kernel(a, k, 0.9, form, form), x, gain)
        twin = grads(lambda a, k: tone_curve_reference(a, k, 0.9, form, form), x, gain)
        for a, b in zip(fused, twin):
            torch.testing.assert_close(a, b, rtol=2e-5, atol=2e-5)


def test_gradient_only_where_asked():
    x = values((5, 5, 3))
    gain = torch.tensor([2.0, 3.0, 4.0], dtype=torch.float64, requires_grad=True)
    (gg,) = torch.autograd.grad(tone_curve_kernel(x, gain).sum(), (gain,))  # x needs none
    (ref,) = torch.autograd.grad(tone_curve_reference(x, gain).sum(), (gain,))
    torch.testing.assert_close(gg, ref, rtol=1e-12, atol=1e-12)
    xg = x.clone().requires_grad_(True)
    (gx,) = torch.autograd.grad(tone_curve_kernel(xg, gain.detach()).sum(), (xg,))  # the gain needs none
    (rx,) = torch.autograd.grad(tone_curve_reference(xg, gain.detach()).sum(), (xg,))
    torch.testing.assert_close(gx, rx, rtol=1e-12, atol=1e-12)


def test_other_layouts_fall_back_to_the_same_values():
    x = values((2, 3, 4, 5))
    gain = torch.rand(1, 3, 4, 1, dtype=torch.float64) + 1.0  # varies along two axes: the twin's broadcast
    torch.testing.assert_close(tone_curve_kernel(x, gain), tone_curve_reference(x, gain), rtol=0, atol=0)
    big = torch.rand(2, 2, 3, 4, 5, dtype=torch.float64) + 1.0  # would enlarge x
    assert tone_curve_kernel(x, big).shape == (2, 2, 3, 4, 5)


def test_non_finite_values_stay_non_finite():
    x = torch.tensor([float("nan"), 0.5, float("inf")], dtype=torch.float64)
    y = tone_curve_kernel(x, torch.tensor(2.0, dtype=torch.float64), 1.0, "open", "open")
    ref = tone_curve_reference(x, torch.tensor(2.0, dtype=torch.float64), 1.0, "open", "open")
    assert torch.isnan(y[0]) and torch.equal(torch.isfinite(y), torch.isfinite(ref))


def test_empty_input():
    x = torch.empty(0, 3, dtype=torch.float64, requires_grad=True)
    y = tone_curve_kernel(x, torch.ones(3, dtype=torch.float64))
    y.sum().backward()
    assert y.shape == (0, 3) and x.grad.shape == (0, 3)


def test_bad_forms_give_one_line():
    x = values((2, 3))
    with pytest.raises(ValueError, match=r"form must be one of clip, open, extended, got 'linear'"):
        tone_curve_kernel(x, torch.ones((), dtype=torch.float64), 1.0, "linear", "clip")
    with pytest.raises(ValueError, match=r"one of clip, open, extended, linear, got 'gamma'"):
        tone_curve_kernel(x, torch.ones((), dtype=torch.float64), 1.0, "clip", "gamma")


def test_kernel_checks_its_gain():
    from retinexgs.render._backend import kernels
    x = values((4, 3))
    with pytest.raises(ValueError, match="gain"):
        kernels().tone_curve_forward(x, torch.ones(2, dtype=torch.float64), 3, 1, 1.0, 0, 0)
    with pytest.raises(TypeError, match="gain must have dtype"):
        kernels().tone_curve_forward(x, torch.ones(3), 3, 1, 1.0, 0, 0)
    with pytest.raises(ValueError, match="forms"):
        kernels().tone_curve_forward(x, torch.ones(3, dtype=torch.float64), 3, 1, 1.0, 0, 4)


# ---- the callers ----------------------------------------------------------------------------------------------
def test_cpu_runs_the_twin_exactly(monkeypatch):
    """On the CPU the callers run the torch twin (faster there, and CPU training unchanged bit for bit)."""
    monkeypatch.setattr(_ToneCurve, "apply", lambda *a: pytest.fail("the kernel ran on the CPU"))
    x, gain = values((3, 4, 3)), torch.tensor([2.0, 3.0, 4.0], dtype=torch.float64)
    assert torch.equal(tone_curve(x, gain, 0.9, "open", "clip"), tone_curve_reference(x, gain, 0.9, "open", "clip"))


def test_exposure_tone_map_is_the_torch_chain():
    g = torch.Generator().manual_seed(7)
    R = torch.rand(6, 5, 3, generator=g, dtype=torch.float64, requires_grad=True)
    L = torch.rand(6, 5, 3, generator=g, dtype=torch.float64, requires_grad=True)
    ref = torch.tensor(0.4, dtype=torch.float64)
    gamma = torch.tensor([1.7, 1.7, 1.7], dtype=torch.float64, requires_grad=True)
    for shoulder in (1.0, 0.85):
        S, Le = ExposureTone().map(R, L, ref, gamma, shoulder=shoulder)
        k = exposure_gain(ref, gamma)
        S_t = linear_to_srgb(highlight_shoulder(k * srgb_to_linear(R * L), shoulder))
        L_t = linear_to_srgb(highlight_shoulder(k * srgb_to_linear(L), shoulder))
        torch.testing.assert_close(S, S_t, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(Le, L_t, rtol=1e-12, atol=1e-12)
        got = torch.autograd.grad((S * 3 + Le).sum(), (R, L, gamma))
        want = torch.autograd.grad((S_t * 3 + L_t).sum(), (R, L, gamma))
        for a, b in zip(got, want):
            torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-12)


def test_exposed_and_linear_light_are_the_torch_curves():
    x = values((1, 3, 8, 8))
    gain = torch.tensor(6.0, dtype=torch.float64)
    torch.testing.assert_close(exposed(x, gain), linear_to_srgb(gain * srgb_to_linear(x, clip=False), clip=False),
                               rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(exposed(x, gain, extended=True),
                               linear_to_srgb_extended(gain * srgb_to_linear_extended(x)), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(to_linear(x, "open"), srgb_to_linear(x, clip=False), rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(to_linear(x, "extended"), srgb_to_linear_extended(x), rtol=1e-12, atol=1e-15)


def test_meter_through_the_kernel_matches_the_torch_path(monkeypatch):
    """highlight_capped_mean takes the fused curves where tone_curve does (the GPU): the same target as its torch
    path (the CPU's), to float32 rounding, with and without the shoulder and where the cap acts or not."""
    from retinexgs.model.tones import fused_curve
    from retinexgs.model.tones.meter import highlight_capped_mean
    g = torch.Generator().manual_seed(7)
    RL = torch.rand(40, 50, 3, generator=g) * torch.tensor([1.0, 0.8, 0.6]) ** 2
    RL[:3] = 1.0  # a blown-out band: the cap acts
    cases = [(0.5, 0.05, 1.0), (0.5, 0.05, 0.8), (0.2, 0.3, 0.8)]
    torch_path = [highlight_capped_mean(RL, *c) for c in cases]
    monkeypatch.setattr(fused_curve, "runs_fused", lambda x: True)
    kernel_path = [highlight_capped_mean(RL, *c) for c in cases]
    for a, b in zip(torch_path, kernel_path):
        assert abs(float(a) - float(b)) < 1e-6
    assert float(torch_path[0]) < 0.5  # the cap acted on this image (else the test compares two constants)
