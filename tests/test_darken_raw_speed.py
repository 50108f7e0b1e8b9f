"""Issue 65: ``darken --raw`` fast. The fast pipeline equals its plain reference bit for bit (same random draws);
the views run in worker processes with one random stream each, so the files do not depend on --jobs; the noise
statistics of the per-view streams are the sensor model's.

Fixtures are small synthetic photos and demo scenes in tmp_path.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from retinexgs.data import raw_sim
from retinexgs.data.camera_raw import demosaic_bilinear, demosaic_bilinear_reference
from retinexgs.data.images import write_image_atomic
from retinexgs.data.raw_sim import CFA_PATTERNS, RawCamera
from retinexgs.data.sensor import SensorModel, darken_scene, srgb_to_linear, view_rng
from retinexgs.demo.synthetic import make_demo_scene
from scenes import run_cli


def _photo(h: int, w: int, levels: int, seed: int = 0) -> np.ndarray:
    """float32 [H, W, 3] as read_image_float returns an 8-bit (levels 255) or 16-bit (65535) photo."""
    codes = np.random.default_rng(seed).integers(0, levels + 1, (h, w, 3))
    return codes.astype(np.float32) / float(levels)


@pytest.mark.filterwarnings("ignore:invalid value encountered")  # 1-pixel sides: no sample of a colour, 0/0
def test_sliced_demosaic_equals_the_correlation_demosaic_bit_for_bit():
    rng = np.random.default_rng(1)
    for h, w in [(1, 1), (1, 5), (2, 2), (3, 4), (5, 3), (6, 7), (9, 8), (31, 22)]:
        for cfa in CFA_PATTERNS:
            for dtype in (np.float64, np.float32):
                x = rng.standard_normal((h, w)).astype(dtype)
                want, got = demosaic_bilinear_reference(x, cfa), demosaic_bilinear(x, cfa)
                assert got.dtype == want.dtype
                assert np.array_equal(got, want, equal_nan=True), (h, w, cfa, dtype)
                # the raw reader's form of the CFA: [2, 2] channel indices
                quad = np.array([{"R": 0, "G": 1, "B": 2}[c] for c in cfa]).reshape(2, 2)
                assert np.array_equal(demosaic_bilinear(x, quad), want, equal_nan=True), (h, w, cfa, dtype)


def test_linear_light_through_the_code_table_equals_the_curve():
    for levels in (255, 65535):
        s = _photo(40, 30, levels, seed=levels)
        assert np.array_equal(raw_sim._srgb_to_linear_codes(s), srgb_to_linear(s.astype(np.float64)))
    odd = np.random.default_rng(2).random((20, 10, 3), dtype=np.float32)  # not codes: the curve as it is
    assert np.array_equal(raw_sim._srgb_to_linear_codes(odd), srgb_to_linear(odd.astype(np.float64)))
    assert np.array_equal(raw_sim._srgb_to_linear_codes(odd.astype(np.float64)), srgb_to_linear(odd.astype(np.float64)))


def test_fast_capture_and_isp_equal_the_reference_bit_for_bit():
    """Same random stream: the same DN mosaic and the same camera image, for 8- and 16-bit photos and a float64
    one, each CFA and bit depth, noisy and noise-free, with a colour cast."""
    models = [SensorModel(), SensorModel(full_well=None), SensorModel(cast=(1.2, 1.0, 0.7), full_well=800.0,
                                                                      read_noise=6.0)]
    photos = [_photo(37, 52, 255), _photo(24, 31, 65535), np.random.default_rng(3).random((26, 26, 3))]
    for cfa, bits in zip(CFA_PATTERNS, (14, 12, 14, 12)):
        cam = RawCamera(bits=bits, cfa=cfa)
        for model in models:
            black = cam.black_level(model.full_well, model.read_noise)
            for srgb in photos:
                want = raw_sim.capture_mosaic_reference(srgb, model, cam, 0.07, np.random.default_rng(5))
                got = raw_sim.capture_mosaic(srgb, model, cam, 0.07, np.random.default_rng(5))
                assert got.dtype == np.uint16 and np.array_equal(got, want), (cfa, model)
                assert np.array_equal(raw_sim.process(got, cam, black), raw_sim.process_reference(got, cam, black))


def _files(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_jobs_1_and_jobs_2_write_identical_files(tmp_path, capsys):
    src = make_demo_scene(tmp_path / "src", n_train=3, n_test=1, width=40, height=30, n_points=100)
    outs = []
    for jobs in (1, 2):
        out = tmp_path / f"j{jobs}"
        code, _, err = run_cli(["darken", "--data", src, "--out", out, "--raw", "--quiet", "--seed", "4",
                                "--jobs", jobs], capsys)
        assert code == 0, err
        outs.append(_files(out))
    assert outs[0].keys() == outs[1].keys() and len([n for n in outs[0] if n.endswith(".dng")]) == 4
    for name in outs[0]:
        assert outs[0][name] == outs[1][name], name
    info = json.loads(outs[0]["sensor.json"])
    assert info["seed"] == 4 and "SeedSequence" in info["rng"]
    assert len(set(info["view_exposures"].values())) == 4  # each view its own exposure


def test_a_view_s_files_depend_on_its_name_and_the_seed_only(tmp_path):
    """The same photo darkened alone or beside others (in another worker) gives the same DNG; another name or
    another seed gives other noise."""
    a, b = tmp_path / "ab", tmp_path / "b"
    for folder in (a, b):
        folder.mkdir()
    photo = (_photo(30, 40, 255) * 255).round().astype(np.uint8)
    for folder, name in ((a, "a.png"), (a, "b.png"), (b, "b.png")):
        write_image_atomic(folder / name, photo)
    model, cam = SensorModel(), RawCamera()
    darken_scene(a, tmp_path / "oa", model, seed=1, progress=False, raw=cam, jobs=2)
    darken_scene(b, tmp_path / "ob", model, seed=1, progress=False, raw=cam, jobs=1)
    darken_scene(b, tmp_path / "ob2", model, seed=2, progress=False, raw=cam, jobs=1)
    dng = lambda out, n: (out / "raw" / n).read_bytes()  # noqa: E731
    assert dng(tmp_path / "oa", "b.dng") == dng(tmp_path / "ob", "b.dng")
    assert dng(tmp_path / "oa", "a.dng") != dng(tmp_path / "oa", "b.dng")
    assert dng(tmp_path / "ob", "b.dng") != dng(tmp_path / "ob2", "b.dng")


def test_per_view_streams_keep_the_noise_statistics():
    """The per-view streams draw the model's noise: on a flat patch, each view's normalised raw has the mean and
    the variance S x + O of the NoiseProfile (within 3 %: 40 000 samples per plane), exposures spread over
    k (1 ± j) uniformly, and two views' noise is uncorrelated (|r| < 0.02)."""
    model = SensorModel(exposure=0.2, exposure_jitter=0.1, full_well=1500.0, read_noise=4.0)
    cam = RawCamera(bits=14, cfa="RGGB")
    black = cam.black_level(model.full_well, model.read_noise)
    span = cam.white_level - black
    s, o = raw_sim.noise_profile(cam, model.full_well, model.read_noise)
    grey = np.full((400, 400, 3), 0.5)
    want = raw_sim.unprocess(grey[:1, :1], cam)[0, 0]
    noises, ks = [], []
    for name in ("low/0000.png", "low/0001.png"):
        rng = view_rng(7, name)
        k = model.view_exposure(rng)
        x = (raw_sim.capture_mosaic(grey, model, cam, k, rng).astype(np.float64) - black) / span
        for i, c in ((0, 0), (1, 2)):  # the R and B planes
            plane = x[i::2, i::2]
            assert plane.mean() == pytest.approx(want[c] * k, rel=0.01)
            assert plane.var() == pytest.approx(s * want[c] * k + o, rel=0.03)
        noises.append(x[0::2, 0::2] - x[0::2, 0::2].mean())
        ks.append(k)
    assert abs(np.corrcoef(noises[0].ravel(), noises[1].ravel())[0, 1]) < 0.02
    k_all = [model.view_exposure(view_rng(7, f"low/{i:04d}.png")) for i in range(2000)]
    assert min(k_all) >= 0.18 and max(k_all) <= 0.22 and np.mean(k_all) == pytest.approx(0.2, rel=0.005)
    assert np.std(k_all) == pytest.approx(0.02 / np.sqrt(3), rel=0.05)  # uniform on ±0.02
    assert ks[0] != ks[1]


def test_bad_jobs_get_one_line(tmp_path, capsys):
    src = make_demo_scene(tmp_path / "src", n_train=2, n_test=1, width=32, height=24, n_points=100)
    for extra, message in ((["--raw", "--jobs", "0"], "--jobs must be at least 1"),
                           (["--jobs", "2"], "--jobs applies only to raw files: add --raw")):
        code, _, err = run_cli(["darken", "--data", src, "--out", tmp_path / "o", "--quiet", *extra], capsys)
        assert code == 2 and message in err and "Traceback" not in err, (extra, err)
        assert len(err.strip().splitlines()) == 1 and not (tmp_path / "o").exists()


def test_bench_darken_runs_and_finds_the_paths_identical(tmp_path, capsys):
    from retinexgs.bench.darken import main

    assert main(["--width", "64", "--height", "48", "--views", "2", "--jobs", "2", "--tmp", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "bit-identical: yes" in out and "darken --raw of 2 views, --jobs 2" in out
    assert list(tmp_path.iterdir()) == []  # its temporary folder is removed


def test_a_killed_worker_gets_one_line():
    """A worker that dies (as when the system kills it for memory) ends the pool with a UserError saying what to do,
    not a BrokenProcessPool traceback."""
    import os

    from retinexgs.data.sensor import map_views
    from retinexgs.errors import UserError

    with pytest.raises(UserError, match="worker process stopped abruptly.*smaller --jobs than 2"):
        map_views(os._exit, [3, 3], 2, False, "darken --raw")
    assert map_views(abs, [-1, 2, -3], 2, False, "x") == [1, 2, 3]  # results in item order


def test_bench_darken_bad_options_get_one_line(tmp_path, capsys):
    """A --photo that does not exist, or --jobs 0, is one usage line (exit 2), not a traceback, and leaves no
    temporary folder."""
    from retinexgs.bench.darken import main

    for extra, message in ((["--photo", str(tmp_path / "missing.jpg")], "no such file"),
                           (["--views", "2", "--jobs", "0"], "--jobs must be at least 1")):
        with pytest.raises(SystemExit) as e:
            main(["--width", "32", "--height", "24", "--tmp", str(tmp_path), *extra])
        err = capsys.readouterr().err
        assert e.value.code == 2 and message in err and "Traceback" not in err, (extra, err)
        assert list(tmp_path.iterdir()) == []
