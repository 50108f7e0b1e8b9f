"""Issue 50 ("A newcomer's third hour"), the ``sfm`` and COLMAP parts: the user's COLMAP files in ``--out`` are
not replaced without ``--force``; truncated or corrupt model files are named before pycolmap reads them (no
gigabyte allocation, no junk cameras, nothing in the cache); a full disk during SfM is one line; a file given as
the photo folder is called a file; mapping progress never counts past the photos; matching says what it does;
a killed run's temporary folder is cleared by the next; the SfM caches are keyed by content.

SfM itself is replaced by a stand-in for pycolmap's three stages (a hand-made reconstruction of the photos),
so these tests take milliseconds; the real pipeline is covered by tests/test_data.py."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import List

import numpy as np
import pytest
from PIL import Image

from retinexgs.data import load_scene
from retinexgs.errors import UserError
from scenes import run_cli

pycolmap = pytest.importorskip("pycolmap")

NAMES = [f"p{i:02d}.png" for i in range(10)]
W, H = 40, 30


def _photo(path: Path, seed: int, shape=(H, W)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.random.default_rng(seed).integers(0, 256, (*shape, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(path, compress_level=0)  # stored: the file size depends on the shape only


def _photos(folder: Path, names=NAMES) -> Path:
    for i, n in enumerate(names):
        _photo(folder / n, i)
    return folder


def _reconstruction(names: List[str], params=(30.0, 20.0, 15.0, 0.01), n_points=5, observed=False):
    """A registered pycolmap model of ``names`` (one SIMPLE_RADIAL camera, cameras on a line); ``observed``: every
    point seen by every photo, as in a real model (SfM's night guard drops photos that share too few points)."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H, params=list(params),
                                                    camera_id=1))
    keypoints = np.full((n_points if observed else 0, 2), 4.0)
    for i, n in enumerate(names):
        w2c = np.hstack([np.eye(3), np.array([[-0.3 * i], [0.0], [0.0]])])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=n, keypoints=keypoints, camera_id=1, image_id=i + 1),
                                         pycolmap.Rigid3d(w2c))
    rng = np.random.default_rng(0)
    for k, p in enumerate(rng.uniform(-1, 1, (n_points, 3)) + [0, 0, 4]):
        track = pycolmap.Track()
        for i in range(len(names) if observed else 0):
            track.add_element(i + 1, k)
        rec.add_point3D(p, track, np.array([10, 20, 30], np.uint8))
    return rec


class FakeColmap:
    """pycolmap with its three SfM stages replaced: extraction writes a stand-in database, matching records its
    call, mapping plays ``script`` on the progress callbacks ('i' initial pair, 'n' next image) and returns a
    model of the photos. Everything else is the real pycolmap."""

    def __init__(self, script: str = "i" + "n" * 8, fail_extract: BaseException = None):
        self.script, self.fail_extract, self.calls = script, fail_extract, []

    def __getattr__(self, name):
        return getattr(pycolmap, name)

    def extract_features(self, db, feature_dir, image_names=(), **kwargs):
        self.calls.append(("extract", Path(feature_dir)))
        if self.fail_extract is not None:
            raise self.fail_extract
        Path(db).write_bytes(b"stand-in database")
        self.names = list(image_names)

    def match_exhaustive(self, db, **kwargs):
        self.calls.append(("match", "exhaustive"))

    def match_sequential(self, db, **kwargs):
        self.calls.append(("match", "sequential"))

    def incremental_mapping(self, db, image_dir, out, options=None, initial_image_pair_callback=None,
                            next_image_callback=None, **kwargs):
        self.calls.append(("map", Path(image_dir)))
        for step in self.script:
            (initial_image_pair_callback if step == "i" else next_image_callback)()
        return {0: _reconstruction(self.names, n_points=20, observed=True)}


@pytest.fixture
def fake(monkeypatch):
    import retinexgs.data.sfm as sfm_module

    f = FakeColmap()
    monkeypatch.setattr(sfm_module, "_pycolmap", lambda: f)
    return f


def _tree(root: Path) -> dict:
    """{relative path: (bytes, mtime_ns)} of every file under ``root``."""
    return {str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file()}


def _one_line_error(code: int, err: str, *says: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("retinexgs sfm: error:")]
    assert len(lines) == 1, err
    for s in says:
        assert s in lines[0], err


def _users_colmap_project(out: Path) -> Path:
    """A folder holding a user's COLMAP output (database.db and sparse/0/*.bin), made without retinexgs."""
    (out / "sparse" / "0").mkdir(parents=True)
    _reconstruction(NAMES[:3]).write_binary(str(out / "sparse" / "0"))
    (out / "database.db").write_bytes(b"the user's COLMAP database")
    return out


# ---- item 1: the user's COLMAP files in --out -------------------------------------------------------------

def test_sfm_refuses_to_replace_the_users_colmap_files(tmp_path, capsys, fake):
    photos = _photos(tmp_path / "photos")
    out = _users_colmap_project(tmp_path / "proj")
    before = _tree(out)
    code, _, err = run_cli(["sfm", "--images", photos, "--out", out], capsys)
    _one_line_error(code, err, str(out), "database.db", "sparse", "--force")
    assert _tree(out) == before and not fake.calls  # nothing touched, SfM not started
    assert not [p for p in out.iterdir() if p.name.startswith(".tmp")]


def test_sfm_force_replaces_the_users_colmap_files(tmp_path, capsys, fake):
    photos = _photos(tmp_path / "photos")
    out = _users_colmap_project(tmp_path / "proj")
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", out, "--force"], capsys)
    assert code == 0, err
    assert (out / "database.db").read_bytes() == b"stand-in database"
    assert "registered views: 10/10" in outp
    assert json.loads((out / "retinexgs_sfm.json").read_text())["signature"] is not None


def test_sfm_reuses_and_replaces_its_own_output_without_force(tmp_path, capsys, fake):
    photos = _photos(tmp_path / "photos")
    out = tmp_path / "proj"
    assert run_cli(["sfm", "--images", photos, "--out", out], capsys)[0] == 0
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", out], capsys)
    assert code == 0 and "(cached)" in outp, err
    n_maps = sum(c[0] == "map" for c in fake.calls)
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", out, "--max-features", "100"], capsys)
    assert code == 0 and "(cached)" not in outp, err  # other options: its own model is recomputed, no --force
    assert sum(c[0] == "map" for c in fake.calls) == n_maps + 1


def test_sfm_help_says_what_force_replaces(capsys):
    code, outp, _ = run_cli(["sfm", "--help"], capsys)
    assert code == 0
    assert "did not make" in " ".join(outp.split())


# ---- item 4: truncated and corrupt COLMAP files -------------------------------------------------------------

@pytest.fixture
def colmap_scene(tmp_path):
    """A COLMAP scene: images/ and a binary model in sparse/0 (as COLMAP >= 3.12 writes it, rigs and frames)."""
    root = tmp_path / "scene"
    _photos(root / "images", NAMES[:4])
    (root / "sparse" / "0").mkdir(parents=True)
    _reconstruction(NAMES[:4], n_points=30).write_binary(str(root / "sparse" / "0"))
    return root


def _cut(path: Path, size) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2] if size == "half" else data + b"\0" if size == "+1" else data[:size])


def test_intact_binary_model_loads(colmap_scene, tmp_path):
    scene = load_scene(colmap_scene, cache_dir=tmp_path / "cache", num_random_points=10)
    assert len(scene.train) == 4 and len(scene.points) == 30


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin"])
@pytest.mark.parametrize("size", [0, 2, "half", "+1"])
def test_truncated_binary_model_file_is_named(colmap_scene, name, size):
    path = colmap_scene / "sparse" / "0" / name
    _cut(path, size)
    with pytest.raises(UserError) as info:
        load_scene(colmap_scene, num_random_points=10)
    msg = str(info.value)
    assert f"{path} is truncated or corrupt (" in msg and "copy it again or re-run retinexgs sfm" in msg, msg
    assert not (colmap_scene / "retinexgs_cache").exists()  # nothing undistorted from junk


def test_huge_point_count_is_refused_without_allocating(colmap_scene):
    # the count field of a damaged points3D.bin says 2^62 points: pycolmap reserved memory for them
    path = colmap_scene / "sparse" / "0" / "points3D.bin"
    data = bytearray(path.read_bytes())
    data[:8] = (1 << 62).to_bytes(8, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(UserError, match=r"points3D\.bin is truncated or corrupt \(says 4611686018427387904 points"):
        load_scene(colmap_scene, num_random_points=10)


def test_truncated_model_through_the_cli_is_one_line(colmap_scene, capsys):
    _cut(colmap_scene / "sparse" / "0" / "points3D.bin", 2)
    code, _, err = run_cli(["train", "--data", colmap_scene, "--out", colmap_scene.parent / "run", "--device",
                            "cpu", "--set", "steps=1"], capsys)
    assert code == 2 and "Traceback" not in err, err
    assert len([ln for ln in err.splitlines() if "error:" in ln]) == 1, err
    assert "points3D.bin is truncated or corrupt" in err and "bad_alloc" not in err, err


def test_negative_focal_length_is_refused_before_the_cache(colmap_scene):
    # structurally sound but insane: f < 0 (junk read from a damaged file); SIMPLE_RADIAL's first parameter
    path = colmap_scene / "sparse" / "0" / "cameras.bin"
    data = bytearray(path.read_bytes())
    data[32:40] = np.float64(-30.0).tobytes()
    path.write_bytes(bytes(data))
    with pytest.raises(UserError, match=r"focal length"):
        load_scene(colmap_scene, num_random_points=10)
    assert not (colmap_scene / "retinexgs_cache").exists()


@pytest.mark.parametrize("name", ["cameras.txt", "images.txt", "points3D.txt"])
def test_truncated_text_model_file_is_named(tmp_path, name):
    root = tmp_path / "scene"
    _photos(root / "images", NAMES[:4])
    (root / "sparse" / "0").mkdir(parents=True)
    _reconstruction(NAMES[:4], n_points=30).write_text(str(root / "sparse" / "0"))
    load_scene(root, cache_dir=tmp_path / "cache", num_random_points=10)  # intact: loads
    path = root / "sparse" / "0" / name
    text = path.read_text()
    body = text.index("\n", text.rindex("#")) + 1  # after the comment header
    path.write_text(text[:body + (len(text) - body) // 2 + 3])  # mid-line
    with pytest.raises(UserError, match=rf"{name} is truncated or corrupt \(line \d+"):
        load_scene(root, num_random_points=10)


# ---- item 5: full disk -------------------------------------------------------------------------------------

def test_sfm_on_a_full_disk_is_one_line_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    import retinexgs.data.sfm as sfm_module
    import retinexgs.fileio as fileio

    photos = _photos(tmp_path / "photos")
    f = FakeColmap(fail_extract=RuntimeError("No registered database factory succeeded"))
    monkeypatch.setattr(sfm_module, "_pycolmap", lambda: f)
    monkeypatch.setattr(fileio, "free_bytes", lambda folder: 12 << 10)  # 12 KiB left
    out = tmp_path / "proj"
    code, _, err = run_cli(["sfm", "--images", photos, "--out", out], capsys)
    _one_line_error(code, err, f"no space left on device writing {out / 'database.db'}", "--out")
    assert "factory" not in err
    assert not out.exists()  # the folder this call made is gone


# ---- item 9: sfm messages, leftovers ------------------------------------------------------------------------

def test_sfm_images_that_is_a_file_says_so(tmp_path, capsys, fake):
    photos = _photos(tmp_path / "photos")
    code, _, err = run_cli(["sfm", "--images", photos / NAMES[0], "--out", tmp_path / "o"], capsys)
    _one_line_error(code, err, "is a file, not a folder")
    assert "does not exist" not in err


def test_mapping_progress_counts_per_model_never_past_the_photos(tmp_path, capsys, fake):
    # COLMAP builds a second model after the first: its callbacks start again (the issue saw "13/10 photos")
    fake.script = "i" + "n" * 8 + "i" + "n"
    code, _, err = run_cli(["sfm", "--images", _photos(tmp_path / "photos"), "--out", tmp_path / "o"], capsys)
    assert code == 0, err
    counts = [tuple(map(int, w.split("/"))) for ln in err.splitlines() if "mapping:" in ln
              for w in ln.replace(",", " ").split() if "/" in w and w.replace("/", "").isdigit()]
    assert counts and all(a <= b == 10 for a, b in counts), err
    assert "model 2" in err, err


def test_matching_says_how_many_pairs_and_how_long(tmp_path, capsys, fake):
    code, _, err = run_cli(["sfm", "--images", _photos(tmp_path / "photos"), "--out", tmp_path / "o"], capsys)
    assert code == 0, err
    assert "matching 45 photo pairs (exhaustive)..." in err and "matched in " in err, err
    code, _, err = run_cli(["sfm", "--images", _photos(tmp_path / "photos"), "--out", tmp_path / "o2",
                            "--matching", "sequential"], capsys)
    assert code == 0 and "photo pairs (sequential)..." in err, err


def test_sequential_pair_count():
    from retinexgs.data.sfm import sequential_pair_count

    assert sequential_pair_count(10, 15, False) == 45 == sequential_pair_count(10, 15, True)
    assert sequential_pair_count(100, 2, False) == 99 + 98
    assert sequential_pair_count(100, 3, True) == 99 + 98 + 97 + 96  # i+1, i+2, i+3 and i+4 (2^2)


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_next_sfm_clears_a_killed_runs_temporary_folder_only(tmp_path, capsys, fake):
    from retinexgs.data.sfm import _host_tag

    photos = _photos(tmp_path / "photos")
    out = tmp_path / "proj"
    assert run_cli(["sfm", "--images", photos, "--out", out], capsys)[0] == 0
    killed = out / f".tmp-sfm-{_dead_pid()}-{_host_tag()}-abc123"
    running = out / f".tmp-sfm-{os.getppid()}-{_host_tag()}-def456"  # a live process: another run
    users = [out / ".tmp-sfm-notes", out / "tmp-sfm-keep", out / f".tmp-sfm-{_dead_pid()}-{_host_tag()}-file"]
    for d in (killed, running):
        (d / "models").mkdir(parents=True)
        (d / "database.db").write_bytes(b"half a database")
    users[0].mkdir()
    users[1].mkdir()
    users[2].write_text("a file, not our folder")
    code, _, err = run_cli(["sfm", "--images", photos, "--out", out], capsys)  # cached: still clears
    assert code == 0, err
    assert not killed.exists()
    assert running.is_dir() and all(p.exists() for p in users)


# ---- caches keyed by content ------------------------------------------------------------------------------

def test_a_photo_replaced_with_an_older_mtime_is_noticed(tmp_path, capsys, fake):
    photos = _photos(tmp_path / "photos")
    out = tmp_path / "proj"
    assert run_cli(["sfm", "--images", photos, "--out", out, "--enhance", "on"], capsys)[0] == 0
    copy = (out / "enhanced" / NAMES[3]).read_bytes()
    st = (photos / NAMES[3]).stat()
    _photo(photos / NAMES[3], 99)  # same name and size, other content, older modification time (cp -p)
    os.utime(photos / NAMES[3], ns=(st.st_atime_ns, st.st_mtime_ns - 10**10))
    assert (photos / NAMES[3]).stat().st_size == st.st_size
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", out, "--enhance", "on"], capsys)
    assert code == 0 and "(cached)" not in outp, err
    assert (out / "enhanced" / NAMES[3]).read_bytes() != copy  # the enhanced copy was made again
