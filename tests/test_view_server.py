"""``retinexgs view`` (issue 14): the missing-extra message and bad addresses (no viser needed), and with viser
installed a real server on 127.0.0.1: it serves the page, renders a frame for a websocket client's camera,
survives 200 junk messages and a disconnect mid-frame, and stops in bounded time."""
import math
import random
import sys
import time
import urllib.request

import pytest

from retinexgs.cli import main
from polling import wait_until
from scenes import tiny_trained_run

TINY = ["steps=2", "checkpoint.every=2", "log.tensorboard=false", "model.sh_degree=0", "model.max_init_points=400",
        "decomposer.method=lime", "loss.enhance_from=1"]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return tiny_trained_run(tmp_path_factory.mktemp("viewsrv"), TINY, n_train=2, width=32, height=24,
                            n_points=400)[1]


def test_missing_viser_names_the_extra(run_dir, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser -> ImportError
    assert main(["view", "--run", str(run_dir), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert 'pip install "retinexgs[view]"' in err and "Traceback" not in err


@pytest.mark.parametrize("args, message", [(["--port", "70000"], "--port must be 0..65535"),
                                           (["--port", "-1"], "--port must be 0..65535"),
                                           (["--host", ""], "--host is empty")])
def test_bad_address_is_refused(run_dir, capsys, args, message):
    assert main(["view", "--run", str(run_dir), "--device", "cpu", *args]) == 2
    assert message in capsys.readouterr().err


def test_not_a_run_folder(tmp_path, capsys):
    assert main(["view", "--run", str(tmp_path), "--device", "cpu"]) == 2
    assert "is not a run folder" in capsys.readouterr().err


def _camera_message(**change):
    msg = dict(type="ViewerCameraMessage", wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -3.0), fov=1.0,
               near=0.01, far=100.0, image_height=24, image_width=32, look_at=(0.0, 0.0, 0.0),
               up_direction=(0.0, -1.0, 0.0))
    msg.update(change)
    return msg


def _wait(cond, seconds=20.0):
    return wait_until(cond, seconds, 0.05)


def test_server_renders_and_survives_junk_and_disconnects(run_dir):
    viser = pytest.importorskip("viser")
    msgpack = pytest.importorskip("msgspec.msgpack")
    from websockets.sync.client import connect

    from retinexgs.viewer.server import view_run

    logs = []
    viewer = view_run(run_dir, port=0, device="cpu", log=logs.append, block=False)
    try:
        assert viewer.url.startswith("http://127.0.0.1:")
        assert urllib.request.urlopen(viewer.url, timeout=5).status == 200
        ws_url = viewer.url.replace("http", "ws")
        proto = [f"viser-v{viser.__version__}"]
        with connect(ws_url, subprotocols=proto, open_timeout=10) as ws:
            ws.send(msgpack.encode(_camera_message()))
            assert _wait(lambda: viewer.frames >= 1), logs
            rng = random.Random(0)
            junk = [dict(position=(math.nan, 0.0, 0.0)), dict(fov=0.0), dict(image_width=-5), dict(image_height=0),
                    dict(image_width=10 ** 6), dict(wxyz=(0.0, 0.0, 0.0, 0.0)), dict(fov=math.inf)]
            for i in range(200):
                ws.send(msgpack.encode(_camera_message(**rng.choice(junk))))
            ws.send(msgpack.encode(_camera_message(position=(0.0, 0.0, -2.5))))  # a good one last
            frames = viewer.frames
            assert _wait(lambda: viewer.frames > frames), logs
        # Random bytes (not a message) and a disconnect mid-frame: only that connection ends.
        with connect(ws_url, subprotocols=proto, open_timeout=10) as ws:
            ws.send(bytes(rng.randrange(256) for _ in range(64)))
        ws = connect(ws_url, subprotocols=proto, open_timeout=10)
        ws.send(msgpack.encode(_camera_message(image_width=320, image_height=240)))
        time.sleep(0.02)
        ws.close()
        assert urllib.request.urlopen(viewer.url, timeout=5).status == 200
        frames = viewer.frames
        with connect(ws_url, subprotocols=proto, open_timeout=10) as ws:
            ws.send(msgpack.encode(_camera_message()))
            assert _wait(lambda: viewer.frames > frames), logs
        assert any("failed: ValueError" in m for m in logs)  # junk was logged, not raised
    finally:
        start = time.time()
        viewer.stop()
        assert time.time() - start < 10


def test_cli_prints_the_url_serves_and_stops_on_ctrl_c(run_dir):
    pytest.importorskip("viser")
    import re
    import signal
    import subprocess

    proc = subprocess.Popen([sys.executable, "-m", "retinexgs", "view", "--run", str(run_dir), "--port", "0",
                             "--device", "cpu"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = None
        for line in proc.stdout:  # the URL line comes once the server listens
            m = re.search(r"retinexgs view: .* at (http://127\.0\.0\.1:\d+)", line)
            if m:
                url = m.group(1)
                break
        assert url, "no URL printed"
        assert urllib.request.urlopen(url, timeout=5).status == 200
        proc.send_signal(signal.SIGINT)
        out = proc.communicate(timeout=20)[0]
        assert proc.returncode == 0 and "Traceback" not in out, out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_the_absolute_gamma_slider_spans_the_runs_gamma_range():
    from types import SimpleNamespace

    from retinexgs.viewer.server import gamma_slider_range
    model = lambda lo, hi: SimpleNamespace(enhancement=SimpleNamespace(g_min=lo, g_max=hi))  # noqa: E731
    assert gamma_slider_range(model(0.25, 2.0)) == (0.12, 2.5)  # the exposure tone (the default)
    assert gamma_slider_range(model(0.1, 1.0)) == (0.05, 1.25)  # the gamma tones
    assert gamma_slider_range(None) == (0.05, 1.5)  # a baseline: the slider is disabled anyway


# ---- issue 36: addresses that cannot be bound fail at once (viser retried them forever, silently) ----------

def _main_within(argv, seconds=60.0):
    """``main(argv)`` in a thread: (exit code, finished in time). A hang fails the test instead of stalling it."""
    import threading

    result = {}
    thread = threading.Thread(target=lambda: result.setdefault("code", main(argv)), daemon=True)
    thread.start()
    thread.join(seconds)
    return result.get("code"), not thread.is_alive()


@pytest.mark.parametrize("args, message", [
    (["--host", "999.1.1.1"], "--host '999.1.1.1' is not an IP address or a host name that resolves"),
    (["--host", "192.0.2.1"], "--host 192.0.2.1: not an address of this machine"),  # TEST-NET-1
    (["--port", "65536"], "--port must be 0..65535"),
])
def test_an_address_that_cannot_be_bound_fails_fast(run_dir, capsys, args, message):
    code, finished = _main_within(["view", "--run", str(run_dir), "--device", "cpu", *args])
    assert finished, "view hung on an address it cannot bind"
    err = capsys.readouterr().err
    assert code == 2 and message in err and "Traceback" not in err, err


def test_a_port_the_user_may_not_bind_fails_fast(run_dir, capsys, monkeypatch):
    """A non-root user binding port 1 (tests run as root here: the bind is refused by a stand-in)."""
    import socket

    def refuse(self, address):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(socket.socket, "bind", refuse)
    code, finished = _main_within(["view", "--run", str(run_dir), "--device", "cpu", "--port", "1"])
    assert finished, "view hung on a port it may not bind"
    err = capsys.readouterr().err
    assert code == 2 and "--port 1: no permission to bind 127.0.0.1:1 (ports below 1024 need root)" in err, err


def test_a_taken_port_still_moves_on_to_the_next_free_one(run_dir):
    pytest.importorskip("viser")
    import socket

    from retinexgs.viewer.server import view_run

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        lines = []
        viewer = view_run(run_dir, "127.0.0.1", port, "cpu", log=lines.append, block=False)
        try:
            got = viewer.server.get_port()
            assert got != port
            # issue 50: the user is told that the port asked for was taken, and which one serves
            assert f"port {port} was taken, so {got} is used" in " ".join(lines), lines
        finally:
            viewer.stop()


def test_sigterm_stops_the_viewer_quietly_with_143(run_dir):
    pytest.importorskip("viser")
    import re
    import signal
    import subprocess

    proc = subprocess.Popen([sys.executable, "-m", "retinexgs", "view", "--run", str(run_dir), "--port", "0",
                             "--device", "cpu"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for line in proc.stdout:
            if re.search(r"retinexgs view: .* at http://", line):
                break
        proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=20)[0]
        assert proc.returncode == 143, out
        assert "retinexgs view: terminated" in out and "Aborted at" not in out and "Traceback" not in out, out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
