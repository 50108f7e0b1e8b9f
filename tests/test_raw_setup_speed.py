"""Issue 65: the set-up of a camera-raw training, faster and bit for bit the same.

What changed and what each test pins: the DNG black map is not built where it repeats every 2x2 quad; the view
store's compaction probes a sample before testing the whole photo; the capture-noise meter encodes only the crop it
measures and reads its photos on threads; the raw views' noise is measured on threads and once per process. Every
fixture is made here (a DNG written by write_dng, a demo scene darkened by ``darken --raw``); the reference of each
comparison is the way set-up did it before (full maps, full reads, one photo at a time), run in the same test.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from retinexgs.data import camera_raw, raw_noise
from retinexgs.data.camera_raw import _dng_black_map, read_raw
from retinexgs.data.dng import write_dng
from retinexgs.data.images import read_image_float
from retinexgs.train import noise as noise_mod
from retinexgs.train import view_store
from retinexgs.train.view_store import PHOTO_LEVELS, compact_photo, photo_table

from scenes import TINY_RUN


class _Tags:  # the DNG tag reader's interface over a dict of tag -> values
    def get(self, ifd, tag, default=None):
        return ifd.get(tag, default)


def _old_quad_check(ifd, h, w):
    """read_raw's decision before the change: the full map, compared with its tiled 2x2 quad."""
    bmap = _dng_black_map(_Tags(), ifd, h, w)
    if bmap is None:
        return None
    quad = np.tile(bmap[:2, :2], (h // 2, w // 2))
    return None if np.allclose(bmap, quad) else bmap


@pytest.mark.parametrize("ifd, skipped", [
    ({50713: [2, 2], 50714: [100, 101, 102, 103]}, True),
    ({50713: [1, 1], 50714: [64]}, True),
    ({50713: [1, 2], 50714: [64, 70]}, True),
    ({50714: [64]}, True),  # no repeat dim: 1x1
    ({50713: [2, 2], 50714: [100, 101, 102, 103], 50715: [1, 2, 3]}, True),  # a delta too short: ignored
    ({50713: [2, 2], 50714: [100, 101, 102, 103], 50715: list(range(24))}, False),  # a delta used: a real map
    ({50713: [2, 2], 50714: [100, 101, 102, 103], 50716: [5] * 24}, False),  # periodic, but built and compared
    ({50713: [4, 4], 50714: list(range(16))}, False),  # a repeat larger than the quad
    ({50713: [2, 2], 50714: [100, float("nan"), 102, 103]}, False),
])
def test_the_black_map_is_skipped_only_where_it_certainly_repeats_every_quad(ifd, skipped):
    """Skipped (None): read_raw's old comparison found it a 2x2 pattern too. Not skipped: the same full map as
    before, which read_raw compares as before."""
    fast = _dng_black_map(_Tags(), ifd, 24, 24, quad_only=True)
    assert (fast is None) == skipped
    if skipped:
        assert _old_quad_check(ifd, 24, 24) is None
    else:
        assert np.array_equal(fast, _dng_black_map(_Tags(), ifd, 24, 24), equal_nan=True)


def test_a_dng_reads_the_same_without_its_full_black_map(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    mosaic = rng.integers(0, 4096, (40, 52)).astype(np.uint16)
    path = write_dng(tmp_path / "a.dng", mosaic, cfa="GRBG", black_level=[64, 65, 66, 67], white_level=4095)
    calls = []
    real = camera_raw._dng_black_map

    def spy(*a, **k):
        out = real(*a, **k)
        calls.append(out)
        return out

    monkeypatch.setattr(camera_raw, "_dng_black_map", spy)
    fast = read_raw(path)
    assert calls == [None]  # the 2x2 pattern: no 40x52 map built
    monkeypatch.setattr(camera_raw, "_dng_black_map", lambda t, i, h, w, quad_only=False: real(t, i, h, w))
    slow = read_raw(path)
    assert fast.black_map is None and slow.black_map is None
    assert np.array_equal(fast.black_level, slow.black_level) and fast.black_level.tolist() == [[64, 65], [66, 67]]
    assert np.array_equal(camera_raw.view_srgb(fast, clip=False), camera_raw.view_srgb(slow, clip=False))


# ---- the store's compact photos -------------------------------------------------------------------------------

def _old_compact(image: torch.Tensor) -> np.ndarray:
    a = np.ascontiguousarray(image.numpy(), dtype=np.float32)
    for name in ("uint8", "uint16"):
        n = PHOTO_LEVELS[name]
        k = np.clip(np.rint(a * n), 0, n).astype(name)
        if np.array_equal(photo_table(name)[k], a):
            return k
    half = a.astype(np.float16)
    return half if np.array_equal(half.astype(np.float32), a) else a


def test_compact_photo_probes_first_but_still_checks_every_value():
    rng = np.random.default_rng(0)
    u8 = rng.integers(0, 256, (64, 80, 3)).astype(np.float32) / 255.0
    u16 = rng.integers(0, 65536, (64, 80, 3)).astype(np.float32) / 65535.0
    f16 = rng.normal(0.2, 0.3, (64, 80, 3)).astype(np.float16).astype(np.float32)
    f32 = rng.random((64, 80, 3), dtype=np.float32)
    almost = u8.copy()
    almost.reshape(-1)[12346] = 0.5  # not k / 255, and off the probe's stride: only the full test sees it
    assert 12346 % max(1, almost.size // view_store._PROBE_VALUES)
    for a, dtype in ((u8, np.uint8), (u16, np.uint16), (f16, np.float16), (f32, np.float32), (almost, np.float32)):
        got, ref = compact_photo(torch.from_numpy(a)), _old_compact(torch.from_numpy(a))
        assert got.dtype == ref.dtype == dtype
        assert np.array_equal(got, ref)


# ---- a raw scene ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def night(tmp_path_factory):
    from retinexgs.cli import main
    from retinexgs.demo.synthetic import make_demo_scene

    base = tmp_path_factory.mktemp("raw_setup")
    src = make_demo_scene(base / "src", n_train=4, n_test=1, width=60, height=44, n_points=200)
    assert main(["darken", "--data", str(src), "--out", str(base / "night"), "--raw", "--quiet"]) == 0
    return base / "night" / "raw"


def _raws(night):
    files = sorted(p for p in (night / "low").iterdir() if p.suffix.lower() == ".dng")
    assert len(files) >= 4
    return files


def test_the_noise_meter_s_crop_is_the_full_view_s_crop_bit_for_bit(night):
    for p in _raws(night):
        full = read_image_float(p)
        crop, lit = noise_mod._measured_photo(p)
        ref = noise_mod.centre_crop(full)
        assert crop.strides == ref.strides and crop.shape == ref.shape
        assert crop.tobytes() == ref.tobytes() and lit == bool(np.any(full > 0))


def _old_capture_noise(photos, downscale=1.0, views=noise_mod.MEASURED_VIEWS, scale=noise_mod.NOISE_SCALE):
    meter = noise_mod.NoiseMeter(torch.device("cpu"), scale)
    for p in photos[::max(1, len(photos) // views)][:views]:
        photo = read_image_float(p)
        noise_mod.check_not_black(photo, p)
        meter.add(photo)
    return meter.result(downscale)


def test_the_capture_noise_is_the_one_of_reading_every_photo_whole_one_at_a_time(night):
    files = _raws(night)
    assert noise_mod.measure_capture_noise(files) == _old_capture_noise(files)
    assert noise_mod.measure_capture_noise(files, 2.0, views=2) == _old_capture_noise(files, 2.0, views=2)


def test_a_black_raw_view_is_still_refused_by_the_noise_meter(night, tmp_path):
    ph = read_raw(_raws(night)[0])
    dark = np.full_like(ph.mosaic, int(ph.black_level.min()))
    path = write_dng(tmp_path / "black.dng", dark, cfa=ph.cfa_pattern, black_level=float(ph.black_level.min()),
                     white_level=int(ph.white_level))
    from retinexgs.errors import UserError
    with pytest.raises(UserError, match="all zero"):
        noise_mod.measure_capture_noise([path])


def test_the_raw_views_noise_is_measured_once_and_again_when_a_file_changes(night, tmp_path, monkeypatch):
    import shutil

    scene = tmp_path / "low"
    shutil.copytree(night / "low", scene)
    files = _raws(tmp_path)
    old = raw_noise.combine_views([raw_noise._one_view_noise(p) for p in files[::max(1, len(files) // 5)][:5]])
    reads = []
    real = raw_noise.read_raw
    monkeypatch.setattr(raw_noise, "read_raw", lambda p: reads.append(p) or real(p))
    first = raw_noise.scene_noise(files)
    n = len(reads)
    assert n == len(files[::max(1, len(files) // 5)][:5])
    assert first == old  # the threads' figures are one-at-a-time's
    second = raw_noise.scene_noise(files)
    assert len(reads) == n and second == first and second is not first  # remembered, a copy
    second.notes.append("a caller's edit")
    assert raw_noise.scene_noise(files).notes == first.notes
    ph = read_raw(files[0])  # replaced by other pixels: measured again
    write_dng(files[0], np.ascontiguousarray(ph.mosaic[::-1]), cfa=ph.cfa_pattern,
              black_level=float(ph.black_level[0, 0]), white_level=int(ph.white_level))
    raw_noise.scene_noise(files)
    assert len(reads) > n


def test_a_streamed_raw_set_up_writes_the_same_store_and_noise_as_before(night, tmp_path, monkeypatch):
    """The whole set-up of a streamed raw training, with and without the changes: the view store's bytes and the
    checkpoint's noise figures are identical."""
    from retinexgs.data.load import load_scene
    from retinexgs.run.config import load_config
    from retinexgs.train import views as views_mod
    from retinexgs.train.trainer import Trainer

    def make(name):
        cfg = load_config(["demo"], [*TINY_RUN, "train.stream_views=always", "decomposer.method=none",
                                     f"data.cache_dir={tmp_path / name / 'cache'}"])
        (tmp_path / name / "run").mkdir(parents=True)
        trainer = Trainer(cfg, load_scene(night), tmp_path / name / "run", "cpu", progress=False, log=lambda s: None)
        store = Path(trainer.views.store.path).read_bytes()
        return store, trainer.noise.state_dict()

    new_store, new_noise = make("new")
    real_map = camera_raw._dng_black_map
    with monkeypatch.context() as m:  # set-up as it was: full maps, full compaction, whole photos, no memory
        m.setattr(camera_raw, "_dng_black_map", lambda t, i, h, w, quad_only=False: real_map(t, i, h, w))
        m.setattr(views_mod, "compact_photo", _old_compact)
        m.setattr("retinexgs.train.capture_setup.measure_capture_noise",
                  lambda photos, downscale=1.0, device=None, scale=noise_mod.NOISE_SCALE, **k:
                  _old_capture_noise(list(photos), downscale, scale=scale))
        m.setattr(raw_noise, "_SCENE_NOISE", {})
        old_store, old_noise = make("old")
    assert new_noise["capture_noise"] is not None and new_noise["raw_noise"] is not None
    assert new_noise == old_noise
    assert new_store == old_store
