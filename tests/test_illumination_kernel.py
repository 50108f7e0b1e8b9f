"""The illumination field's training kernels (retinexgs/model/illumination_kernel.py,
csrc/include/rgs/illumination_train.h) against the torch field on the CPU: values and every gradient in float64,
finite differences, float32, the layouts of the saved buffers, bad inputs."""
import copy

import pytest
import torch

from retinexgs.model.illumination import IlluminationField
from retinexgs.model.illumination_kernel import (_IlluminationKernels, _layout, illumination_at, kernels_apply,
                                                 kernels_unsupported)
from retinexgs.render._backend import kernels
from test_fused_colors import SHAPES, make_field

CENTER = (0.3, -0.2, 2.5)


def _inputs(n=257, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = (torch.randn(n, 3, generator=g, dtype=dtype) * 1.5).requires_grad_(True)
    return means, torch.tensor(CENTER, dtype=dtype)


def _both(field, means, center, g_out):
    """(torch's output and gradients, the kernels'): means' gradient, then each parameter's."""
    params = [p for p in field.parameters() if p.requires_grad]
    results = []
    for fn in (lambda: field(means, IlluminationField.view_dirs(means, center)),
               lambda: kernels_apply(field, means, center)):
        out = fn()
        grads = torch.autograd.grad(out, [means] + params, g_out, allow_unused=True)
        results.append((out.detach(), [torch.zeros_like(p) if gr is None else gr for p, gr in zip([means] + params, grads)]))
    return results


@pytest.mark.parametrize("view_dependent", [True, False])
@pytest.mark.parametrize("shape", SHAPES)
def test_kernels_match_the_torch_field_in_float64(shape, view_dependent):
    field = make_field(shape, view_dependent=view_dependent)
    means, center = _inputs()
    g_out = torch.randn(means.shape[0], 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    (ref, ref_grads), (got, got_grads) = _both(field, means, center, g_out)
    assert torch.allclose(got, ref, rtol=0, atol=1e-13)
    names = ["means"] + [n for n, p in field.named_parameters() if p.requires_grad]
    for name, r, k in zip(names, ref_grads, got_grads):
        assert torch.allclose(k, r, rtol=1e-10, atol=1e-12), name


def test_kernels_gradcheck():
    """Finite differences of the kernels' function in float64: the centres and every weight and bias at once."""
    shape = (3, 2, 8, 2, 4)
    field = make_field(shape)
    means, center = _inputs(n=9, seed=3)
    params = []
    for m in [m for m in field.trunk if isinstance(m, torch.nn.Linear)] + [m for m in field.head if isinstance(m, torch.nn.Linear)]:
        params += [m.weight.detach().clone().requires_grad_(True), m.bias.detach().clone().requires_grad_(True)]
    fn = lambda m, *ps: _IlluminationKernels.apply(shape, field.bound, m, center, *ps)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (means, *params))


def test_kernels_float32_agree_with_float64():
    field = make_field(SHAPES[0])
    means, center = _inputs()
    g_out = torch.randn(means.shape[0], 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    (_, _), (got64, grads64) = _both(field, means, center, g_out)
    field32 = copy.deepcopy(field).float()
    m32 = means.detach().float().requires_grad_(True)
    (ref32, ref_grads32), (got32, grads32) = _both(field32, m32, center.float(), g_out.float())
    assert (got32.double() - got64).abs().max() < 1e-5
    for k, r in zip(grads32, ref_grads32):
        scale = r.abs().max().clamp_min(1e-6)
        assert (k - r).abs().max() / scale < 1e-4


def test_saved_buffers_follow_the_layout():
    """A holds each Linear's input then a row of ones; D's rows are the layers' output gradients."""
    shape = SHAPES[0]
    field = make_field(shape)
    means, center = _inputs(n=11)
    from retinexgs.model.inference import pack_illumination
    rgb, A = kernels().illumination_forward(means.detach(), center, list(shape), field.bound, pack_illumination(field))
    ins, outs, a_in, d_out, (aw, dw) = _layout(tuple(shape))
    chunk = kernels().illum_chunk
    assert A.shape == (aw, chunk) and aw == sum(i + 1 for i in ins) and dw == sum(outs)
    assert torch.equal(A[:, 11:], torch.zeros_like(A[:, 11:]))  # the padding to whole chunks
    for l, n_in in enumerate(ins):
        assert torch.equal(A[a_in[l] + n_in, :11], torch.ones(11, dtype=A.dtype))
    # the first layer's input is the encoding of means / bound
    from retinexgs.model.illumination import positional_encoding
    want = positional_encoding(means.detach() / field.bound, shape[0])
    assert torch.allclose(A[:ins[0], :11].t(), want, atol=1e-14)


def test_illumination_at_keeps_torch_on_the_cpu(monkeypatch):
    field = make_field(SHAPES[0])
    means, center = _inputs(n=5)
    calls = []
    import retinexgs.model.illumination_kernel as ik
    monkeypatch.setattr(ik, "kernels_apply", lambda *a: calls.append(1))
    out = illumination_at(field, means, center)
    assert calls == [] and out.shape == (5, 3)
    assert torch.equal(out, field(means, IlluminationField.view_dirs(means, center)))


def test_bad_inputs_one_line():
    field = make_field(SHAPES[0])
    assert kernels_unsupported(field) is None
    means, center = _inputs(n=4)
    from retinexgs.model.inference import pack_illumination
    w = pack_illumination(field)
    with pytest.raises(ValueError, match="center"):
        kernels().illumination_forward(means.detach(), center[:2], list(SHAPES[0]), 2.0, w)
    with pytest.raises(ValueError, match="depth up to 8"):
        kernels().illumination_train_layout([2, 2, 8, 9, 4])
    with pytest.raises(ValueError, match="bound"):
        kernels().illumination_forward(means.detach(), center, list(SHAPES[0]), 0.0, w)
    with pytest.raises(ValueError, match="A"):
        kernels().illumination_backward(means.detach(), center, list(SHAPES[0]), 2.0, w, torch.zeros(3, 4, dtype=w.dtype),
                                        torch.zeros(4, 3, dtype=w.dtype), torch.zeros(4, 3, dtype=w.dtype))
