"""The decomposition reads the next photos on threads while one is decomposed (retinex/cache.py READ_AHEAD): the
same entries, values and report as one photo at a time; a photo's error comes when its turn comes; a photo whose
entry is on disk is not read."""
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from retinexgs.errors import UserError
from retinexgs.retinex import cache


def _photos(folder: Path, n: int = 6):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        p = folder / f"{i:04d}.png"
        Image.fromarray((rng.random((20, 24, 3)) * 80).astype(np.uint8)).save(p)
        paths.append(p)
    return paths


def _run(paths, root, **kw):
    report = {}
    out = [(r.clone(), l.clone()) for r, l in cache.iter_decompositions(paths, "lime", None, root, "cpu",
                                                                         progress=False, report=report, **kw)]
    return out, report


@pytest.mark.parametrize("ahead", [1, 3])
def test_reading_ahead_gives_what_one_at_a_time_gives(tmp_path, monkeypatch, ahead):
    paths = _photos(tmp_path / "low")
    monkeypatch.setattr(cache, "READ_AHEAD", 0)  # at least one worker: the same path the loop had, in turn
    base, base_report = _run(paths, tmp_path / "a")
    monkeypatch.setattr(cache, "READ_AHEAD", ahead)
    read = []
    real = cache.read_image
    monkeypatch.setattr(cache, "read_image", lambda p, *a, **k: read.append(Path(p).name) or real(p, *a, **k))
    got, report = _run(paths + paths[:1], tmp_path / "b")  # the first photo twice: its second turn is a hit
    assert [k for k in report if k != "folder"] == [k for k in base_report if k != "folder"]
    assert (report["computed"], report["reused"]) == (6, 1)
    for (r0, l0), (r1, l1) in zip(base + base[:1], got):
        assert torch.equal(r0, r1) and torch.equal(l0, l1)
    assert sorted(read) == sorted(p.name for p in paths + paths[:1])  # the duplicate was read ahead, then dropped
    read.clear()
    again, report = _run(paths, tmp_path / "b")  # every entry on disk: nothing read
    assert read == [] and report["reused"] == 6 and all(torch.equal(a[0], b[0]) for a, b in zip(again, got))


def test_a_bad_photo_fails_when_its_turn_comes(tmp_path, monkeypatch):
    paths = _photos(tmp_path / "low", 5)
    paths[3].write_bytes(b"not a png")
    monkeypatch.setattr(cache, "READ_AHEAD", 3)
    done = []
    with pytest.raises(UserError):
        for hit in cache.iter_decompositions(paths, "lime", None, tmp_path / "c", "cpu", progress=False):
            done.append(hit)
    assert len(done) == 3  # the three before it were decomposed and yielded first
    assert len(list((tmp_path / "c").rglob("*.npz"))) == 3


def test_entries_written_behind_are_on_disk_and_the_same_photo_twice_in_a_row_is_reused(tmp_path):
    """The entries are written on a thread while the next photo is decomposed (cache._WriteBehind): when the
    iteration ends every entry is on disk, and a photo repeated at once waits for its entry instead of being
    decomposed again."""
    paths = _photos(tmp_path / "low", 3)
    report = {}
    got = [(r.clone(), l.clone()) for r, l in cache.iter_decompositions(
        [paths[0], paths[0], paths[1], paths[2]], "lime", None, tmp_path / "c", "cpu", progress=False,
        report=report)]
    assert (report["computed"], report["reused"]) == (3, 1)
    assert all(Path(f).is_file() for f in report["files"])
    assert torch.equal(got[0][0], got[1][0]) and torch.equal(got[0][1], got[1][1])


def test_a_failed_entry_write_is_raised_by_the_iteration(tmp_path, monkeypatch):
    paths = _photos(tmp_path / "low", 3)

    def fail(path, *a, **k):
        raise UserError(f"cannot write the cache folder {path.parent}: No space left on device")

    monkeypatch.setattr(cache, "save_entry", fail)
    with pytest.raises(UserError, match="No space left"):
        list(cache.iter_decompositions(paths, "lime", None, tmp_path / "c", "cpu", progress=False))


def test_produced_ahead_keeps_order_values_and_errors():
    assert list(cache.produced_ahead(iter(range(50)), depth=2)) == list(range(50))

    def items():
        yield 1
        yield 2
        raise UserError("photo 3 is unreadable")

    got = []
    with pytest.raises(UserError, match="photo 3"):
        for x in cache.produced_ahead(items()):
            got.append(x)
    assert got == [1, 2]  # the error where its item would have come


def test_produced_ahead_closed_early_stops_its_thread_and_closes_the_source():
    import threading
    import time

    made, closed = [], []

    def items():
        try:
            for i in range(1000):
                made.append(i)
                yield i
        finally:
            closed.append(threading.current_thread().name)

    it = cache.produced_ahead(items(), depth=1, name="test-ahead")
    assert next(it) == 0
    it.close()
    for _ in range(100):
        if closed:
            break
        time.sleep(0.05)
    assert closed == ["test-ahead"] and len(made) <= 3  # one given, at most one queued and one being made
    for _ in range(100):  # the thread ends right after closing its source
        if not [t for t in threading.enumerate() if t.name == "test-ahead"]:
            break
        time.sleep(0.05)
    assert not [t for t in threading.enumerate() if t.name == "test-ahead"]


def test_ctrl_c_while_the_thread_is_inside_torch_exits_cleanly(tmp_path):
    """The producer is waited for when its consumer stops: a thread left inside torch at the interpreter's exit
    aborted the process ("terminate called without an active exception") on a Ctrl-C during the set-up."""
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "child.py"
    script.write_text(
        "import sys, torch\n"
        "from retinexgs.retinex.cache import produced_ahead\n"
        "torch.set_num_threads(1)\n"
        "def items():\n"
        "    while True:\n"
        "        a = torch.rand(300, 300)\n"
        "        for _ in range(200):\n"
        "            a = torch.tanh(a @ a)\n"
        "        yield a\n"
        "print('ready', flush=True)\n"
        "try:\n"
        "    for x in produced_ahead(items()):\n"
        "        pass\n"
        "except KeyboardInterrupt:\n"
        "    print('interrupted', flush=True)\n"
        "    sys.exit(130)\n")
    p = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "ready"
    time.sleep(1.0)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 130 and "interrupted" in out, (p.returncode, out, err)
    assert "terminate called" not in err and "Abort" not in err, err
