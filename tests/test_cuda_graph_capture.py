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
