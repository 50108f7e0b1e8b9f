"""Issue 52, stage 3a: scenes whose photos are camera raw files load, pose and train with the JPEG commands.

Fixtures: tiny demo scenes made in tmp_path, turned into DNGs by ``darken --raw`` or by the simulator's pieces
(retinexgs.data.raw_sim) and ``write_dng``; never the shared data.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from retinexgs.data import camera_raw, images
from retinexgs.data.dng import write_dng
from retinexgs.data.load import load_scene
from retinexgs.data.raw_sim import RawCamera, capture_mosaic, write_raw_view
from retinexgs.data.sensor import SensorModel
from retinexgs.demo.synthetic import make_demo_scene
from scenes import TINY_RUN, run_cli

W, H = 48, 36


@pytest.fixture(scope="module")
def night(tmp_path_factory) -> Path:
    """``darken --raw`` of a 48x36 demo scene (3 train, 1 test): NIGHT/raw (low/*.dng) and NIGHT/jpeg."""
    base = tmp_path_factory.mktemp("raw_scene")
    src = make_demo_scene(base / "src", n_train=3, n_test=1, width=W, height=H, n_points=200)
    from retinexgs.cli import main
    assert main(["darken", "--data", str(src), "--out", str(base / "night"), "--raw", "--quiet"]) == 0
    return base / "night"


def _copy(night: Path, tmp_path: Path) -> Path:
    """A private copy of the raw scene (a test that edits it leaves the module's fixture alone)."""
    dst = tmp_path / "raw"
    shutil.copytree(night / "raw", dst)
    return dst


def _one_line_error(code: int, err: str, *words: str) -> str:
    assert code == 2, err
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("retinexgs")]
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def _train(scene: Path, out: Path, capsys):
    sets = [a for s in TINY_RUN for a in ("--set", s)]
    return run_cli(["train", "--data", scene, "--out", out, "--config", "demo", *sets, "--device", "cpu",
                    "--quiet"], capsys)


# ---- a raw LOM scene ------------------------------------------------------------------------------------------

def test_a_raw_lom_scene_loads_full_size_and_pairs_with_its_truth(night, capsys):
    raw = night / "raw"
    capsys.readouterr()
    scene = load_scene(raw)
    err = capsys.readouterr().err
    assert "raw photos: 4 camera raw views" in err and "factors" in err  # the exposure factors, logged
    assert len(scene.train) == 3 and len(scene.test) == 1
    for v in scene.train + scene.test:
        assert v.image_path.suffix == ".dng" and v.paired_path == raw / "high" / (v.image_path.stem + ".png")
        assert (v.width, v.height) == (W, H) == images.image_size(v.image_path)
        img = images.read_image_float(v.image_path)
        assert img.shape == (H, W, 3) and img.dtype == np.float32 and 0.0 <= img.min() and img.max() <= 1.0
        # full precision: not 8-bit (nor 16-bit) levels
        assert not np.allclose(img * 255, np.round(img * 255), atol=1e-4)
        # 8-bit callers round, as for a 16-bit PNG
        assert np.array_equal(images.read_image(v.image_path), np.clip(np.rint(img * 255), 0, 255).astype(np.uint8))
    # a raw view is the same capture as the camera JPEG beside it (both from one mosaic): close, at its size
    jpeg = images.read_image_float(night / "jpeg" / "low" / "0000.png")
    rawv = images.read_image_float(raw / "low" / "0000.dng")
    factor = camera_raw.folder_exposure(raw / "low").factors["0000.dng"]
    assert 0.8 < factor < 1.2
    assert abs(float(jpeg.mean()) - float(rawv.mean())) < 0.1


def test_a_raw_scene_trains_and_evaluates_through_the_cli(night, tmp_path, capsys):
    code, _, err = _train(night / "raw", tmp_path / "run", capsys)
    assert code == 0, err
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    scored = [v for v in metrics["views"] if v["view"].endswith(".dng")]  # the raw test view, against high/
    assert len(scored) == 1 and np.isfinite(scored[0]["psnr"]) and scored[0]["psnr"] > 5.0
    assert any((tmp_path / "run" / "checkpoints").iterdir())


# ---- exposure normalisation -----------------------------------------------------------------------------------

def _ramp(w: int = 64, h: int = 48) -> np.ndarray:
    x = np.linspace(0.15, 0.85, w)[None, :, None]
    y = np.linspace(0.9, 1.0, h)[:, None, None]
    return np.clip(x * y * np.array([1.0, 0.9, 0.8]), 0, 1) * np.ones((h, w, 3))


def test_views_at_exposures_k_and_2k_read_the_same(tmp_path):
    cam = RawCamera()
    clean, noisy = SensorModel(full_well=None, read_noise=0.0), SensorModel(full_well=4000.0, read_noise=2.0)
    for name, model in (("clean", clean), ("noisy", noisy)):
        folder = tmp_path / name
        folder.mkdir()
        rng = np.random.default_rng(3)
        for i, k in enumerate((0.2, 0.4)):
            write_raw_view(folder / f"v{i}.dng", capture_mosaic(_ramp(), model, cam, k, rng), cam, model, k)
        fe = camera_raw.folder_exposure(folder)
        assert fe.factors == pytest.approx({"v0.dng": 2 / 3, "v1.dng": 4 / 3}) and fe.missing == []
        a, b = (images.read_image_float(folder / f"v{i}.dng") for i in range(2))
        if name == "clean":
            assert np.abs(a - b).max() < 2e-3
        else:  # within the noise: the mean agrees, the difference is zero-mean
            assert abs(float(a.mean() - b.mean())) < 3e-3 and np.abs(a - b).mean() < 0.05
    # without the normalisation the two differ by the exposure (the test can fail)
    a, b = (camera_raw.view_srgb(camera_raw.read_raw(tmp_path / "clean" / f"v{i}.dng")) for i in range(2))
    assert b.mean() > a.mean() + 0.05


def test_a_raw_files_cache_key_follows_its_exposure_factor(tmp_path):
    """Every cache keys a raw view by its bytes AND the exposure factor it is read with: a third raw file of
    another exposure in the folder moves the folder's median, so the same bytes read as other pixels."""
    from retinexgs.data.undistort import image_key, source_digest

    cam, model = RawCamera(), SensorModel(full_well=None, read_noise=0.0)
    rng = np.random.default_rng(0)
    for i, k in enumerate((0.2, 0.4)):
        write_raw_view(tmp_path / f"v{i}.dng", capture_mosaic(_ramp(), model, cam, k, rng), cam, model, k)
    before = image_key(tmp_path / "v0.dng")
    assert before != source_digest(tmp_path / "v0.dng")  # not the bytes alone
    write_raw_view(tmp_path / "v2.dng", capture_mosaic(_ramp(), model, cam, 1.6, rng), cam, model, 1.6)
    assert image_key(tmp_path / "v0.dng") != before
    png = tmp_path / "plain.png"  # any other photo: its bytes alone
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(png)
    assert image_key(png) == source_digest(png)


def test_a_raw_file_without_exposure_metadata_gets_factor_1_and_one_warning(night, tmp_path, capsys):
    raw = _copy(night, tmp_path)
    photo = camera_raw.read_raw(raw / "low" / "0001.dng")
    write_dng(raw / "low" / "0001.dng", photo.mosaic, cfa=photo.cfa_pattern, black_level=float(photo.black_level[0, 0]),
              white_level=int(photo.white_level), as_shot_neutral=tuple(1 / photo.white_balance),
              color_matrix1=photo.xyz_to_cam, make=photo.make, model=photo.model)  # no EXIF exposure
    capsys.readouterr()
    load_scene(raw)
    err = capsys.readouterr().err
    warnings = [ln for ln in err.splitlines() if ln.startswith("warning:") and "exposure" in ln]
    assert len(warnings) == 1 and "low/0001.dng" in warnings[0] and "factor 1" in warnings[0], err
    assert camera_raw.folder_exposure(raw / "low").factors["0001.dng"] == 1.0


# ---- poses: sfm on raw files, RAW + JPEG ---------------------------------------------------------------------

def test_sfm_on_a_folder_of_dngs_extracts_features_from_full_size_png_previews(night, tmp_path, monkeypatch):
    """COLMAP cannot read raw files: run_sfm always writes their previews (bright, denoised, full size, PNG bytes
    under the raw file's name), extracts features from them and gives the mapper that folder. Full SfM on
    synthetic views may not register, so the mapper is replaced by one that checks what it was given."""
    import pycolmap

    from retinexgs.data import sfm
    from retinexgs.errors import UserError

    folder = tmp_path / "dngs"
    folder.mkdir()
    for p in sorted((night / "raw" / "low").glob("*.dng")):
        shutil.copy2(p, folder / p.name)
    seen = {}

    def mapper(db, image_path, out, **kwargs):
        seen["image_path"] = Path(image_path)
        database = pycolmap.Database.open(str(db))
        seen["keypoints"] = {im.name: database.num_keypoints_for_image(im.image_id)
                             for im in database.read_all_images()}
        seen["cameras"] = {(c.width, c.height) for c in database.read_all_cameras()}
        database.close()
        for p in sorted(Path(image_path).glob("*.dng")):
            seen.setdefault("previews", []).append((p.read_bytes()[:8], np.asarray(Image.open(p).convert("RGB"))))
        return {}

    monkeypatch.setattr(pycolmap, "incremental_mapping", mapper)
    with pytest.raises(UserError, match="could not build a model"):
        sfm.run_sfm(folder, tmp_path / "sfm", enhance=False, progress=None)
    assert seen["image_path"] == tmp_path / "sfm" / "enhanced"
    assert sorted(seen["keypoints"]) == [f"{i:04d}.dng" for i in range(4)]
    assert min(seen["keypoints"].values()) > 0, seen["keypoints"]
    assert seen["cameras"] == {(W, H)}
    for magic, rgb in seen["previews"]:
        assert magic == b"\x89PNG\r\n\x1a\n" and rgb.shape == (H, W, 3)
        assert rgb.mean() > 1.5 * images.read_image(folder / "0000.dng").mean()  # brightened


def test_a_raw_plus_jpeg_folder_poses_from_the_jpegs_and_trains_on_the_raw_files(night, tmp_path, monkeypatch,
                                                                                  capsys):
    from retinexgs.data import load, sfm

    folder = tmp_path / "capture"
    folder.mkdir()
    for p in sorted((night / "raw" / "low").glob("*.dng")):
        shutil.copy2(p, folder / p.name)
        shutil.copy2(night / "jpeg" / "low" / (p.stem + ".png"), folder / (p.stem + ".png"))
    pairs = sfm.raw_jpeg_pairs(images.list_images(folder))
    assert {r.name: j.name for r, j in pairs.items()} == {f"{i:04d}.dng": f"{i:04d}.png" for i in range(4)}
    model_dir = night / "raw" / "colmap_sparse" / "0"  # the demo's model, naming the NNNN.png photos
    called = {}

    def fake_sfm(image_dir, out, **kwargs):
        called["dir"] = Path(image_dir)
        return sfm.SfmResult(model_dir, Path(image_dir), 4, [], 0, 0.0, False)

    monkeypatch.setattr(load, "run_sfm", fake_sfm)
    capsys.readouterr()
    scene = load_scene(folder, reader="sfm", cache_dir=tmp_path / "cache")
    err = capsys.readouterr().err
    assert "RAW + JPEG pairs" in err and "poses from the JPEGs" in err
    assert called["dir"] == folder
    views = scene.train + scene.test
    assert len(views) == 4 and all(v.image_path.suffix == ".dng" for v in views)


def test_run_sfm_on_raw_plus_jpeg_reads_only_the_jpegs(night, tmp_path, monkeypatch):
    import pycolmap

    from retinexgs.data import sfm
    from retinexgs.errors import UserError

    folder = tmp_path / "capture"
    folder.mkdir()
    for p in sorted((night / "raw" / "low").glob("*.dng")):
        shutil.copy2(p, folder / p.name)
        shutil.copy2(night / "jpeg" / "low" / (p.stem + ".png"), folder / (p.stem + ".png"))
    seen = {}

    def extract(db, image_path, image_names=None, **kwargs):
        seen["names"], seen["path"] = list(image_names), Path(image_path)
        raise RuntimeError("stop here")

    monkeypatch.setattr(pycolmap, "extract_features", extract)
    messages = []
    with pytest.raises(RuntimeError, match="stop here"):
        sfm.run_sfm(folder, tmp_path / "sfm", enhance=False, progress=messages.append)
    assert seen["names"] == [f"{i:04d}.png" for i in range(4)] and seen["path"] == folder
    assert any("RAW + JPEG" in m for m in messages)
    (folder / "0000.png").unlink()  # 0000.dng now has no partner: mixed, refused
    with pytest.raises(UserError, match="mixes camera raw files"):
        sfm.run_sfm(folder, tmp_path / "sfm2", progress=None)


# ---- bad input, one line each -----------------------------------------------------------------------------------

def test_raw_and_other_photos_in_one_split_are_refused(night, tmp_path, capsys):
    raw = _copy(night, tmp_path)
    (raw / "low" / "0001.dng").unlink()
    shutil.copy2(night / "jpeg" / "low" / "0001.png", raw / "low" / "0001.png")
    path = raw / "transforms_train.json"
    data = json.loads(path.read_text())
    for f in data["frames"]:
        f["file_path"] = f["file_path"].replace("0001.dng", "0001.png")
    path.write_text(json.dumps(data))
    code, _, err = _train(raw, tmp_path / "run", capsys)
    _one_line_error(code, err, "mixes camera raw files and other photos", "low/0001.png")
    assert not (tmp_path / "run").exists()


def _rewrite(path: Path, **changes) -> None:
    p = camera_raw.read_raw(path)
    args = dict(cfa=p.cfa_pattern, black_level=float(p.black_level[0, 0]), white_level=int(p.white_level),
                as_shot_neutral=tuple(1 / p.white_balance), color_matrix1=p.xyz_to_cam,
                exposure_time=p.exposure_time, iso=p.iso, f_number=p.f_number, make=p.make, model=p.model)
    mosaic = changes.pop("mosaic", p.mosaic)
    args.update(changes)
    write_dng(path, mosaic, **args)


def test_raw_photos_of_two_cameras_in_one_split_are_refused(night, tmp_path, capsys):
    raw = _copy(night, tmp_path)
    _rewrite(raw / "low" / "0001.dng", make="Nikon", model="D850")  # a training view
    code, _, err = _train(raw, tmp_path / "run", capsys)
    _one_line_error(code, err, "different cameras", "Nikon D850")


def test_raw_photos_of_two_sizes_in_one_split_are_refused(night, tmp_path, capsys):
    raw = _copy(night, tmp_path)
    p = camera_raw.read_raw(raw / "low" / "0001.dng")  # a training view
    _rewrite(raw / "low" / "0001.dng", mosaic=np.ascontiguousarray(p.mosaic[:, :W - 4]))
    code, _, err = _train(raw, tmp_path / "run", capsys)
    _one_line_error(code, err, "different sizes", f"{W - 4}x{H}")


def test_a_raw_file_libraw_cannot_read_is_named_in_one_line(night, tmp_path, capsys):
    raw = _copy(night, tmp_path)
    data = (raw / "low" / "0001.dng").read_bytes()
    (raw / "low" / "0001.dng").write_bytes(data[: len(data) // 2])  # truncated
    code, _, err = _train(raw, tmp_path / "run", capsys)
    _one_line_error(code, err, "0001.dng", "truncated")
    (raw / "low" / "0001.dng").write_bytes(b"\x00" * 4096)  # not a raw file at all
    code, _, err = _train(raw, tmp_path / "run", capsys)
    _one_line_error(code, err, "0001.dng")
