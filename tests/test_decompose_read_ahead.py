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
