"""retinexgs.render.cuda_graphs.capture: the collector is paused during a capture and restored after (CPU: the
capture itself is stubbed; on the GPU the capture sites run it for real in the test_cuda*.py tests)."""
import gc
import threading

import pytest
import torch

from retinexgs.render import cuda_graphs


class _FakeGraph:
    """Stands in for torch.cuda.graph: records whether the collector was on while 'capturing'."""

    def __init__(self, seen, barrier=None):
        self.seen, self.barrier = seen, barrier

    def __enter__(self):
        self.seen.append(gc.isenabled())
        if self.barrier is not None:
            self.barrier.wait(timeout=10)

    def __exit__(self, *exc):
        self.seen.append(gc.isenabled())
        return False


@pytest.fixture
def fake_graph(monkeypatch):
    seen = []
    monkeypatch.setattr(torch.cuda, "graph", lambda graph, **kw: _FakeGraph(seen, graph))
    return seen


@pytest.mark.parametrize("was_on", [True, False])
def test_capture_pauses_the_collector_and_restores_it(fake_graph, was_on):
    (gc.enable if was_on else gc.disable)()
    try:
        with cuda_graphs.capture(None):
            pass
        assert fake_graph == [False, False]
        assert gc.isenabled() is was_on
    finally:
        gc.enable()


def test_capture_restores_the_collector_when_the_capture_raises(fake_graph):
    gc.enable()
    with pytest.raises(RuntimeError, match="boom"):
        with cuda_graphs.capture(None):
            raise RuntimeError("boom")
    assert gc.isenabled()


def test_overlapping_captures_keep_the_collector_off_until_the_last_ends(fake_graph):
    gc.enable()
    inside = threading.Barrier(2)
    release = threading.Event()
    states = []

    def other():
        with cuda_graphs.capture(None):
            inside.wait(timeout=10)
            release.wait(timeout=10)

    t = threading.Thread(target=other)
    t.start()
    with cuda_graphs.capture(None):
        inside.wait(timeout=10)
    states.append(gc.isenabled())  # the other capture is still running
    release.set()
    t.join(timeout=10)
    assert states == [False]
    assert gc.isenabled()


# ---- cuda_graphs.Branch: a parallel branch of a captured graph -------------------------------------------------
def _two_chains(x: torch.Tensor, w: torch.Tensor, branch_cls):
    """A loss of two independent chains (the second inside a Branch), and its gradients in x and w."""
    branch = branch_cls(x)
    with branch:
        b = w
        for _ in range(20):
            b = torch.sin(b) * 1.01 + 0.1
        second = (b * x.detach().mean()).square().sum()
    a = x
    for _ in range(20):
        a = torch.tanh(a) + 0.01 * a
    first = a.square().mean()
    branch.join(second)
    total = first + second
    gx, gw = torch.autograd.grad(total, [x, w])
    return torch.stack([total.detach(), first.detach(), second.detach()]), gx, gw


def test_a_branch_outside_a_capture_changes_nothing():
    """On the CPU (and eagerly on the GPU) a Branch forks nothing: the same values, bit for bit."""
    x = torch.randn(64, dtype=torch.float64, requires_grad=True)
    w = torch.randn(8, dtype=torch.float64, requires_grad=True)

    class NoBranch:
        def __init__(self, like):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

        def join(self, *outputs):
            pass
    for got, want in zip(_two_chains(x, w, cuda_graphs.Branch), _two_chains(x, w, NoBranch)):
        assert torch.equal(got, want)
    assert cuda_graphs.Branch(x)._side is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_a_captured_branch_replays_the_eager_values_and_gradients():
    """Forward and backward of two chains, one on a Branch, captured and replayed on new inputs: every replay
    equals the eager computation of the same inputs (the branch joined, its gradients back on the main stream)."""
    g = torch.Generator(device="cuda").manual_seed(0)
    x = torch.randn(4096, device="cuda", generator=g).requires_grad_(True)
    w = torch.randn(512, device="cuda", generator=g).requires_grad_(True)
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(2):
            _two_chains(x, w, cuda_graphs.Branch)
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with cuda_graphs.capture(graph):
        out = _two_chains(x, w, cuda_graphs.Branch)
    for seed in range(1, 4):
        gen = torch.Generator(device="cuda").manual_seed(seed)
        with torch.no_grad():
            x.copy_(torch.randn(4096, device="cuda", generator=gen))
            w.copy_(torch.randn(512, device="cuda", generator=gen))
        graph.replay()
        want = _two_chains(x, w, cuda_graphs.Branch)  # eager: no capture, no fork
        for got, ref in zip(out, want):
            torch.testing.assert_close(got, ref, rtol=1e-6, atol=1e-7)
