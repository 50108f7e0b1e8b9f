"""``retinexgs train --view`` (issue 14): the live viewer renders frames while the trainer runs, frames and steps
take turns through the step gate (cheap when nobody is connected), the server stops with training, and a
missing viser or a bad port is refused before any work."""
import sys
import threading
import time
import urllib.error
import urllib.request

import pytest

from retinexgs.cli import main
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.train.runner import train_run
from retinexgs.viewer.live import StepGate
from polling import wait_until

TINY = ["checkpoint.every=1000", "log.tensorboard=false", "model.sh_degree=0", "model.max_init_points=400",
        "decomposer.method=lime", "loss.enhance_from=0.5"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("live") / "scene", n_train=2, n_test=1, width=32, height=24,
                           n_points=400)


def test_step_gate_costs_little_and_serialises():
    gate = StepGate()
    calls = []
    step = gate.wrap(lambda i: calls.append(i) or i)
    start = time.perf_counter()
    for i in range(20000):
        assert step(i) == i
    per_step = (time.perf_counter() - start) / 20000
    assert len(calls) == 20000 and per_step < 50e-6  # a training step takes milliseconds
    inside = []
    with gate.frame():  # a frame holds the gate: a step waits for it
        t = threading.Thread(target=lambda: inside.append(step(-1)))
        t.start()
        time.sleep(0.1)
        assert inside == []
    t.join(5)
    assert inside == [-1]


def test_train_view_renders_while_training_and_stops_after(scene, tmp_path, monkeypatch):
    pytest.importorskip("viser")
    msgpack = pytest.importorskip("msgspec.msgpack")
    import viser
    from websockets.sync.client import connect

    import retinexgs.viewer.live as live

    viewers = []
    real = live.start_live_viewer
    monkeypatch.setattr(live, "start_live_viewer", lambda *a, **k: viewers.append(real(*a, **k)) or viewers[-1])
    logs, result = [], {}
    steps = 300
    thread = threading.Thread(target=lambda: result.update(metrics=train_run(
        scene, tmp_path / "run", ["demo"], TINY + [f"steps={steps}"], "cpu", progress=False, log=logs.append,
        on_trainer=live.live_viewer("127.0.0.1", 0))))
    thread.start()
    try:
        assert _wait(lambda: viewers), logs
        viewer = viewers[0]
        assert any(viewer.url in m for m in logs)
        msg = dict(type="ViewerCameraMessage", wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -3.0), fov=1.0,
                   near=0.01, far=100.0, image_height=24, image_width=32, look_at=(0.0, 0.0, 0.0),
                   up_direction=(0.0, -1.0, 0.0))
        with connect(viewer.url.replace("http", "ws"), subprotocols=[f"viser-v{viser.__version__}"]) as ws:
            ws.send(msgpack.encode(msg))
            assert _wait(lambda: viewer.frames >= 1), (viewer.frames, list(viewer._clients), logs)
            assert thread.is_alive(), "training ended before the viewer drew a frame; raise steps"
        assert not any("failed" in m for m in logs), logs
    finally:
        thread.join(120)
    assert not thread.is_alive()
    assert "metrics" in result  # training and evaluation completed normally
    with pytest.raises((urllib.error.URLError, ConnectionError, OSError)):
        urllib.request.urlopen(viewer.url, timeout=2)  # the server stopped with training


def _wait(cond, seconds=30.0):
    return wait_until(cond, seconds, 0.05)


@pytest.mark.parametrize("extra, message, block_viser", [
    (["--view"], 'pip install "retinexgs[view]"', True),
    (["--view", "--view-port", "99999"], "--port must be 0..65535", False),
])
def test_train_view_refuses_before_any_work(scene, tmp_path, monkeypatch, capsys, extra, message, block_viser):
    if block_viser:
        monkeypatch.setitem(sys.modules, "viser", None)
    out = tmp_path / "run"
    assert main(["train", "--data", str(scene), "--out", str(out), "--device", "cpu", "--quiet", *extra]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
