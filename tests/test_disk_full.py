"""Issue 36: a full disk is one clear error for every writer (checkpoints, the decomposition cache, PNG and MP4
renders, PLY exports, config/metrics/log files), naming the file and the free space; the file it replaces
survives and no temporary is left. The write callables are made to fail as they do on a full disk: OSError
ENOSPC/EDQUOT, or torch's zip writer's RuntimeError (``unexpected pos``, ``file write failed``)."""
from __future__ import annotations

import errno
import io
import shutil
from pathlib import Path

import pytest
import torch

from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write, atomic_write_text
from scenes import run_cli

TINY = ["steps=3", "checkpoint.every=3", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
        "model.max_init_points=300", "decomposer.method=lime", "eval.lpips=false"]
FULL = [OSError(errno.ENOSPC, "No space left on device"), OSError(errno.EDQUOT, "Disk quota exceeded"),
        RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 4416 vs 4304"),
        RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed")]
IDS = ["ENOSPC", "EDQUOT", "torch-unexpected-pos", "torch-file-write-failed"]


_cli = run_cli


def _no_temps(folder: Path) -> bool:
    return not [p for p in Path(folder).rglob("*") if p.name.startswith(".tmp-") or p.name.endswith(".tmp")]


def _says_full(err: str, path: Path, option: str = "--out") -> None:
    assert "Traceback" not in err, err
    assert f"no space left on device writing {path} (" in err and "MiB free on that disk)" in err, err
    assert f"free some space or write elsewhere with {option}" in err, err


def _fail_with(exc):
    def fail(*a, **k):
        f = next((x for x in a if isinstance(x, io.IOBase)), None)
        if f is not None:
            f.write(b"partial bytes")  # some bytes reach the temporary file first
        raise exc
    return fail


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("demo") / "scene", n_train=3, n_test=1, width=24, height=18,
                           n_points=200)


@pytest.fixture(scope="module")
def run(tmp_path_factory, demo):
    from retinexgs.train.runner import train_run

    base = tmp_path_factory.mktemp("run")
    shutil.copytree(demo, base / "scene")
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        train_run(base / "scene", base / "run", ["demo"], TINY, "cpu", progress=False, log=lambda s: None)
    finally:
        torch.set_num_threads(n)
    return base / "run"


# ---- atomic_write: every writer that goes through it (config.yaml, metrics.json, PNGs, PLY, cache entries) ----

@pytest.mark.parametrize("exc", FULL, ids=IDS)
def test_atomic_write_on_a_full_disk_names_the_file_and_keeps_the_old_one(tmp_path, exc):
    target = tmp_path / "metrics.json"
    target.write_text("old")
    with pytest.raises(UserError) as info:
        atomic_write(target, _fail_with(exc))
    _says_full(str(info.value), target)
    assert target.read_text() == "old" and _no_temps(tmp_path)


def test_a_full_disk_when_the_temporary_file_is_made(tmp_path, monkeypatch):
    import tempfile

    monkeypatch.setattr(tempfile, "mkstemp", _fail_with(OSError(errno.ENOSPC, "No space left on device")))
    with pytest.raises(UserError) as info:
        atomic_write_text(tmp_path / "config.yaml", "x: 1\n", elsewhere="--set data.cache_dir=DIR")
    _says_full(str(info.value), tmp_path / "config.yaml", "--set data.cache_dir=DIR")


@pytest.mark.parametrize("exc", [ValueError("a bug"), OSError(errno.EIO, "Input/output error"),
                                 RuntimeError("something else")], ids=["ValueError", "EIO", "RuntimeError"])
def test_other_write_errors_are_not_called_a_full_disk(tmp_path, exc):
    from retinexgs.fileio import free_bytes

    assert free_bytes(tmp_path) > 64 << 20  # this test needs a disk that is not nearly full
    with pytest.raises(type(exc)) as info:
        atomic_write(tmp_path / "f.bin", _fail_with(exc))
    assert not isinstance(info.value, UserError) and _no_temps(tmp_path)


def test_train_log_line_on_a_full_disk(tmp_path):
    from retinexgs.train.trainer import _append_record

    class Full:
        name = str(tmp_path / "train_log.jsonl")

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(UserError) as info:
        _append_record(Full(), {"step": 1})
    _says_full(str(info.value), tmp_path / "train_log.jsonl")


# ---- checkpoints (torch.save, its own temporary name) -------------------------------------------------------

@pytest.mark.parametrize("exc", FULL, ids=IDS)
def test_checkpoint_on_a_full_disk_keeps_the_previous_one(tmp_path, monkeypatch, exc):
    from retinexgs.run.checkpoint import list_checkpoints, load_checkpoint, save_checkpoint

    first = save_checkpoint(tmp_path, 1, {"step": 1, "model": {"w": torch.ones(3)}})
    monkeypatch.setattr(torch, "save", _fail_with(exc))
    with pytest.raises(UserError) as info:
        save_checkpoint(tmp_path, 2, {"step": 2, "model": {"w": torch.zeros(3)}})
    _says_full(str(info.value), tmp_path / "checkpoints" / "step_000002.pt")
    assert list_checkpoints(tmp_path) == [first] and load_checkpoint(first)["step"] == 1
    assert _no_temps(tmp_path)


def test_train_on_a_full_disk_is_one_line_not_a_traceback(demo, tmp_path, capsys, monkeypatch):
    shutil.copytree(demo, tmp_path / "scene")
    monkeypatch.setattr(torch, "save", _fail_with(FULL[2]))  # what torch.save into a full tmpfs raised
    code, _, err = _cli(["train", "--data", tmp_path / "scene", "--out", tmp_path / "run", "--device", "cpu",
                         "--config", "demo", *[a for t in TINY for a in ("--set", t)]], capsys)
    assert code == 2, err
    _says_full(err, tmp_path / "run" / "checkpoints" / "step_000003.pt")
    assert not (tmp_path / "run" / "checkpoints").exists()  # the failed first checkpoint's folder is removed too


# ---- the decomposition cache --------------------------------------------------------------------------------

def test_cache_entry_on_a_full_disk_names_the_cache_option(demo, tmp_path, capsys, monkeypatch):
    from retinexgs.retinex import cache as rcache

    scene = tmp_path / "scene"
    shutil.copytree(demo, scene)
    code, _, err = _cli(["decompose", "--data", scene, "--method", "lime", "--quiet"], capsys)
    assert code == 0, err
    entry = sorted((scene / "retinex_cache").rglob("*.npz"))[0]
    entry.write_bytes(b"truncated")  # invalid: must be rewritten
    monkeypatch.setattr(rcache.np, "savez", _fail_with(FULL[0]))
    code, _, err = _cli(["decompose", "--data", scene, "--method", "lime", "--quiet"], capsys)
    assert code == 2, err
    _says_full(err, entry, "--cache DIR (or --set data.cache_dir=DIR)")
    assert entry.read_bytes() == b"truncated" and _no_temps(scene)


# ---- renders (PNG, MP4) and exports (PLY) -------------------------------------------------------------------

def test_render_png_on_a_full_disk(run, tmp_path, capsys, monkeypatch):
    from PIL import Image

    out = tmp_path / "renders"
    code, _, err = _cli(["render", "--run", run, "--out", out, "--device", "cpu", "--quiet"], capsys)
    assert code == 0, err
    png = sorted(out.rglob("*.png"))[0]
    before = png.read_bytes()
    monkeypatch.setattr(Image.Image, "save", _fail_with(FULL[0]))
    code, _, err = _cli(["render", "--run", run, "--out", out, "--device", "cpu", "--quiet", "--force"], capsys)
    assert code == 2, err
    _says_full(err, png)
    assert png.read_bytes() == before and _no_temps(out)


def test_ply_export_on_a_full_disk(run, tmp_path, capsys, monkeypatch):
    import plyfile

    ply = tmp_path / "model.ply"
    ply.write_bytes(b"the previous export")
    monkeypatch.setattr(plyfile.PlyData, "write", _fail_with(FULL[1]))
    code, _, err = _cli(["export", "--run", run, "--out", ply, "--device", "cpu", "--quiet", "--force"], capsys)
    assert code == 2, err
    _says_full(err, ply)
    assert ply.read_bytes() == b"the previous export" and _no_temps(tmp_path)


def test_video_on_a_full_disk(run, tmp_path, capsys, monkeypatch):
    import imageio

    class FullDisk:  # ffmpeg writes the file itself: on a full disk it dies and the pipe to it breaks
        def append_data(self, frame):
            raise OSError(errno.EPIPE, "[Errno 32] Broken pipe\n\nFFMPEG STDERR OUTPUT:\n"
                                       "av_interleaved_write_frame(): No space left on device")

        def close(self):
            pass

    monkeypatch.setattr(imageio, "get_writer", lambda *a, **k: FullDisk())
    mp4 = tmp_path / "orbit.mp4"
    code, _, err = _cli(["render", "--run", run, "--path", "orbit", "--frames", "2", "--out", mp4, "--device", "cpu",
                         "--quiet"], capsys)
    assert code == 2, err
    _says_full(err, mp4)
    assert list(tmp_path.iterdir()) == []  # no video, no temporary folder
