"""The fused tone curve's CUDA kernel against the CPU one, values and gradients (run on a GPU machine; skipped
cleanly where there is none)."""
import itertools

import pytest
import torch

from retinexgs.render import has_cuda
from retinexgs.model.tones.fused_curve import tone_curve, tone_curve_kernel
from test_tone_curve import FORMS_IN, FORMS_OUT, grads, values

pytestmark = pytest.mark.skipif(not (torch.cuda.is_available() and has_cuda()),
                                reason="needs a CUDA GPU and retinexgs built with its CUDA kernels")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("form_in,form_out", list(itertools.product(FORMS_IN, FORMS_OUT)))
@pytest.mark.parametrize("knee", [1.0, 0.8])
def test_cuda_matches_cpu(dtype, form_in, form_out, knee):
    x = values((3, 3, 211, 333), dtype)  # 634k elements: many blocks, a ragged last one
    gain = torch.tensor([2.0, 9.0, 0.7], dtype=dtype).view(1, 3, 1, 1)
    cpu = grads(lambda a, k: tone_curve_kernel(a, k, knee, form_in, form_out), x, gain)
    gpu = grads(lambda a, k: tone_curve(a, k, knee, form_in, form_out), x.cuda(), gain.cuda())
    # float32 within a few ulps (--use_fast_math's powf/expf); the gain's gradient is a sum over 634k elements
    # in another order
    tols = [1e-12] * 3 if dtype == torch.float64 else [1e-5, 1e-5, 1e-4]
    for a, b, tol in zip(cpu, gpu, tols):
        torch.testing.assert_close(b.cpu(), a, rtol=tol, atol=tol)


def test_cuda_last_axis_gain_and_graph_capture():
    """The per-channel gain on the last axis (the tone's [H,W,3]), captured in a CUDA graph as the losses are."""
    x = values((90, 160, 3), torch.float32).cuda().requires_grad_(True)
    gain = torch.tensor([3.0, 4.0, 5.0], device="cuda", requires_grad=True)
    out = {}

    def step():
        y = tone_curve(x, gain, 0.9)
        out["grads"] = torch.autograd.grad(y.square().sum(), (x, gain))
        out["y"] = y.detach()

    s = torch.cuda.Stream()
    s.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(s):
        step()  # warm up outside the capture
    torch.cuda.current_stream().wait_stream(s)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        step()
    graph.replay()
    torch.cuda.synchronize()
    y_ref = tone_curve_kernel(x.detach().cpu(), gain.detach().cpu(), 0.9)
    xc, gc = x.detach().cpu().requires_grad_(True), gain.detach().cpu().requires_grad_(True)
    gx, gg = torch.autograd.grad(tone_curve_kernel(xc, gc, 0.9).square().sum(), (xc, gc))
    torch.testing.assert_close(out["y"].cpu(), y_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out["grads"][0].cpu(), gx, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out["grads"][1].cpu(), gg, rtol=1e-4, atol=1e-3)


def test_cuda_meter_matches_cpu():
    """The exposure meter (highlight_capped_mean) on the GPU, through the fused curves, against the CPU's torch path."""
    from retinexgs.model.tones.meter import highlight_capped_mean
    g = torch.Generator().manual_seed(8)
    RL = torch.rand(300, 400, 3, generator=g) ** 2
    RL[:20] = 1.0
    for knee in (1.0, 0.8):
        cpu = highlight_capped_mean(RL, 0.5, 0.05, knee)
        gpu = highlight_capped_mean(RL.cuda(), 0.5, 0.05, knee)
        assert abs(float(cpu) - float(gpu)) < 1e-5
