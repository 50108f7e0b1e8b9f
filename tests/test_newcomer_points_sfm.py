"""Issue 62, items 2, 3 and 8c: a COLMAP model's points are matched to a transforms scene's views by stem in any
format (never assumed to share their frame: too few matches warn and start from random points); the photos SfM
leaves out are named, and too few registered is refused unless ``--min-registered`` allows it; raw files of two
sizes are refused before SfM; a model folder holding only some of its files is named instead of running SfM.

Small synthetic fixtures only; SfM's three stages are replaced by a stand-in (a hand-made reconstruction of the
photos it is told to register), so nothing here runs a real SfM."""
from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import numpy as np
import pytest
import yaml
from PIL import Image

from retinexgs.data import load_scene
from retinexgs.data.transforms_json import read_transforms_scene
from retinexgs.errors import UserError
from scenes import run_cli

pycolmap = pytest.importorskip("pycolmap")

W, H = 40, 30
STEMS = [f"p{i:02d}" for i in range(6)]
# camera centres that are not on one line (a line leaves the frames' rotation about it undetermined)
CENTRES = np.array([[0.0, 0.0, 0.0], [0.6, 0.0, 0.1], [0.0, 0.5, -0.1], [0.7, 0.6, 0.2], [-0.4, 0.3, 0.0],
                    [0.3, -0.5, 0.1]])


def _photo(path: Path, seed: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)).save(path)


def _reconstruction(names: List[str], centres: np.ndarray, n_points: int = 20):
    """A pycolmap model registering ``names``, camera i at ``centres[i]`` looking down +z (OpenCV axes)."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=W, height=H,
                                                    params=[30.0, 30.0, W / 2, H / 2], camera_id=1))
    for i, n in enumerate(names):
        w2c = np.hstack([np.eye(3), -centres[i].reshape(3, 1)])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=n, camera_id=1, image_id=i + 1), pycolmap.Rigid3d(w2c))
    rng = np.random.default_rng(0)
    for p in rng.uniform(-1, 1, (n_points, 3)) + [0, 0, 4]:
        rec.add_point3D(p, pycolmap.Track(), np.array([10, 20, 30], np.uint8))
    return rec


# the JSON's world is the model's under this similarity (LOM's JSON poses are such a copy of COLMAP's)
SCALE = 2.5
ROT = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
SHIFT = np.array([1.0, -2.0, 0.5])


def _lom_scene(root: Path, suffix: str, model_names: List[str], json_centres: Optional[np.ndarray] = None,
               model_centres: Optional[np.ndarray] = None) -> Path:
    """A LOM-like scene: ``low/<stem><suffix>`` photos, a transforms_train.json whose poses are the model's under
    (SCALE, ROT, SHIFT) (or at ``json_centres``), and ``colmap_sparse/0`` registering ``model_names`` at CENTRES
    (or ``model_centres``)."""
    frames = []
    for i, stem in enumerate(STEMS):
        _photo(root / "low" / f"{stem}{suffix}", i)
        c = SCALE * ROT @ CENTRES[i] + SHIFT if json_centres is None else json_centres[i]
        c2w = np.eye(4)
        c2w[:3, :3] = ROT  # the model's camera rotation is the identity
        c2w[:3, 3] = c
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL axes, as the JSON stores them
        frames.append({"file_path": f"low/{stem}{suffix}", "transform_matrix": c2w.tolist()})
    (root / "transforms_train.json").write_text(json.dumps({"fl_x": 30.0, "fl_y": 30.0, "frames": frames}))
    model = root / "colmap_sparse" / "0"
    model.mkdir(parents=True)
    centres = CENTRES[:len(model_names)] if model_centres is None else model_centres
    _reconstruction(model_names, centres).write_binary(str(model))
    return root


def _model_points(root: Path) -> np.ndarray:
    from retinexgs.data.colmap import read_model

    return read_model(root / "colmap_sparse" / "0").points


def _warnings(err: str) -> List[str]:
    return [ln for ln in err.splitlines() if ln.startswith("warning:")]


# ---- item 2: the model's points in the views' frame ------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_points_follow_photos_saved_in_another_format_by_stem(tmp_path, capsys, suffix):
    # the issue: a LOM scene's photos saved as .png, the model keeps the camera's .JPG names
    root = _lom_scene(tmp_path / "scene", suffix, [f"{s}.JPG" for s in STEMS])
    scene = read_transforms_scene(root)
    assert scene.points_source == "colmap"
    expected = SCALE * _model_points(root) @ ROT.T + SHIFT
    np.testing.assert_allclose(scene.points, expected, atol=1e-6)
    assert not _warnings(capsys.readouterr().err)


def test_a_model_naming_the_photos_exactly_still_maps_its_points(tmp_path, capsys):
    root = _lom_scene(tmp_path / "scene", ".png", [f"{s}.png" for s in STEMS])
    scene = read_transforms_scene(root)
    np.testing.assert_allclose(scene.points, SCALE * _model_points(root) @ ROT.T + SHIFT, atol=1e-6)
    assert not _warnings(capsys.readouterr().err)


def test_too_few_matches_warn_and_start_from_random_points(tmp_path, capsys):
    # no view matches the model's images: the frames were assumed equal and the points landed elsewhere, silently
    root = _lom_scene(tmp_path / "scene", ".png", [f"IMG_{i}.JPG" for i in range(len(STEMS))])
    capsys.readouterr()
    scene = load_scene(root, cache_dir=tmp_path / "cache", num_random_points=50)
    err = capsys.readouterr().err
    lines = _warnings(err)
    assert len(lines) == 1, err
    assert "only 0 of the 6 views match" in lines[0] and "random points" in lines[0], err
    assert "colmap_sparse/0" in lines[0] and "IMG_0.JPG" in lines[0] and "p00.png" in lines[0], err
    assert scene.points_source == "random" and len(scene.points) == 50
    assert np.allclose(scene.colors.numpy(), 0.5)  # the random points' grey, not the model's colours


def test_two_matches_are_too_few(tmp_path, capsys):
    names = [f"{s}.JPG" for s in STEMS[:2]] + [f"IMG_{i}.JPG" for i in range(2, len(STEMS))]
    root = _lom_scene(tmp_path / "scene", ".png", names)
    capsys.readouterr()
    scene = read_transforms_scene(root)
    assert scene.points_source == "random" and scene.points is None
    assert "only 2 of the 6 views match" in _warnings(capsys.readouterr().err)[0]


def test_ambiguous_stems_match_by_full_name_only(tmp_path, capsys):
    # the model names a.JPG and a.png (two images, two poses): a view a.png is a.png, never a.JPG
    names = [f"{s}.JPG" for s in STEMS] + [f"{s}.png" for s in STEMS]
    rec_centres = np.vstack([CENTRES + [5.0, 5.0, 5.0], CENTRES])  # the .JPG images elsewhere
    root = _lom_scene(tmp_path / "scene", ".png", names, model_centres=rec_centres)
    scene = read_transforms_scene(root)
    np.testing.assert_allclose(scene.points, SCALE * _model_points(root) @ ROT.T + SHIFT, atol=1e-6)
    # photos saved as .tif: a stem names two model images, so nothing matches by stem: random, and said why
    tif = _lom_scene(tmp_path / "scene2", ".tif", names, model_centres=rec_centres)
    capsys.readouterr()
    scene = read_transforms_scene(tif)
    line = _warnings(capsys.readouterr().err)[0]
    assert scene.points is None and "only 0 of the 6 views match" in line and "name several files" in line, line


def test_views_sharing_a_stem_do_not_take_one_model_image(tmp_path, capsys):
    from retinexgs.data.colmap import match_views_to_model, read_model
    from retinexgs.data.declared import DeclaredView

    root = _lom_scene(tmp_path / "scene", ".png", [f"{s}.JPG" for s in STEMS])
    scene = read_transforms_scene(root)
    model = read_model(root / "colmap_sparse" / "0")
    v = scene.train[0]
    twin = DeclaredView("low/p00.tif", v.image.with_suffix(".tif"), v.camera, np.eye(4))  # another photo, one stem
    pairs, ambiguous = match_views_to_model(model, scene.train + [twin])
    assert ambiguous == ["p00"]
    assert sorted(Path(im.name).stem for im, _ in pairs) == STEMS[1:]


def test_centres_that_do_not_agree_warn_and_start_from_random_points(tmp_path, capsys):
    # views matched by stem to images of another reconstruction: no similarity maps one rig onto the other
    wrong = np.random.default_rng(3).uniform(-1, 1, (len(STEMS), 3))
    root = _lom_scene(tmp_path / "scene", ".png", [f"{s}.JPG" for s in STEMS], json_centres=wrong)
    capsys.readouterr()
    scene = read_transforms_scene(root)
    line = _warnings(capsys.readouterr().err)[0]
    assert scene.points is None and "do not agree up to a similarity" in line and "random points" in line, line


# ---- item 8c: a model folder with only some of its files ----------------------------------------------------

@pytest.mark.parametrize("sub", ["colmap_sparse/0", "sparse/0"])
def test_a_model_folder_without_cameras_and_images_is_named(tmp_path, capsys, sub):
    root = tmp_path / "scene"
    for i, s in enumerate(STEMS):
        _photo(root / "images" / f"{s}.png", i)
    model = root / sub
    model.mkdir(parents=True)
    _reconstruction([f"{s}.png" for s in STEMS], CENTRES).write_binary(str(model))
    for name in ("cameras.bin", "images.bin", "rigs.bin", "frames.bin"):
        (model / name).unlink()
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    code, _, err = run_cli(["train", "--data", root, "--out", tmp_path / "run", "--device", "cpu",
                            "--set", "steps=1"], capsys)
    assert code == 2 and "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    assert f"COLMAP model {model} is incomplete" in lines[0], err
    assert "points3D.bin" in lines[0] and "cameras.bin, images.bin" in lines[0], err
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before  # no SfM wrote into the scene
    assert not (tmp_path / "run").exists()


def test_a_text_model_without_cameras_is_named(tmp_path):
    root = tmp_path / "scene"
    _photo(root / "images" / "p00.png", 0)
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "sparse" / "0" / "images.txt").write_text("# empty\n")
    with pytest.raises(UserError, match=r"holds images\.txt but not cameras\.txt, points3D\.txt"):
        load_scene(root)


# ---- item 3: SfM that drops photos ---------------------------------------------------------------------------

PHOTOS = [f"p{i:02d}.png" for i in range(10)]


class FakeColmap:
    """pycolmap with its SfM stages replaced: mapping returns a model registering ``registered`` of the photos it
    extracted features from. Everything else is the real pycolmap."""

    def __init__(self, registered: int):
        self.registered, self.maps = registered, 0

    def __getattr__(self, name):
        return getattr(pycolmap, name)

    def extract_features(self, db, feature_dir, image_names=(), **kwargs):
        Path(db).write_bytes(b"stand-in database")
        self.names = sorted(image_names)

    def match_exhaustive(self, db, **kwargs):
        pass

    def incremental_mapping(self, db, image_dir, out, **kwargs):
        self.maps += 1
        return {0: _reconstruction(self.names[:self.registered], np.resize(CENTRES, (len(self.names), 3)) +
                                   np.arange(len(self.names))[:, None] * [0.0, 0.0, 0.01])}


@pytest.fixture
def photos(tmp_path) -> Path:
    for i, n in enumerate(PHOTOS):
        _photo(tmp_path / "photos" / n, i)
    return tmp_path / "photos"


def _fake(monkeypatch, registered: int) -> FakeColmap:
    import retinexgs.data.sfm as sfm_module

    f = FakeColmap(registered)
    monkeypatch.setattr(sfm_module, "_pycolmap", lambda: f)
    return f


def _one_error(code: int, err: str) -> str:
    assert code == 2 and "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    return lines[0]


def test_sfm_registering_2_of_10_is_refused_naming_the_dropped_and_kept_for_the_flag(photos, tmp_path, capsys,
                                                                                     monkeypatch):
    fake = _fake(monkeypatch, 2)
    out = tmp_path / "proj"
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", out], capsys)
    line = _one_error(code, err)
    assert "registered only 2 of 10 photos" in line and "--min-registered 0.5" in line, line
    assert "not registered: " + ", ".join(PHOTOS[2:]) in line and "--min-registered 0.2" in line, line
    assert not _warnings(err), err  # the names are in the error, not also in a warning
    assert (out / "sparse" / "0" / "images.bin").is_file()  # kept: the flag uses it without another SfM run
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", out, "--min-registered", "0"], capsys)
    assert code == 0, err
    assert "registered views: 2/10" in outp and "(cached)" in outp and fake.maps == 1
    lines = _warnings(err)
    assert len(lines) == 1 and "SfM registered 2 of 10 photos" in lines[0], err
    assert "not registered, left out of the scene: " + ", ".join(PHOTOS[2:]) in lines[0], err
    # the share the error proposes is accepted, and a cached model is checked again without the flag
    assert run_cli(["sfm", "--images", photos, "--out", out, "--min-registered", "0.2"], capsys)[0] == 0
    code, _, err = run_cli(["sfm", "--images", photos, "--out", out], capsys)
    assert "registered only 2 of 10" in _one_error(code, err) and fake.maps == 1


def test_sfm_registering_most_photos_warns_naming_the_dropped(photos, tmp_path, capsys, monkeypatch):
    _fake(monkeypatch, 8)
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", tmp_path / "proj"], capsys)
    assert code == 0 and "registered views: 8/10" in outp, err
    lines = _warnings(err)
    assert len(lines) == 1 and lines[0].endswith("not registered, left out of the scene: p08.png, p09.png"), err
    _fake(monkeypatch, 10)
    code, _, err = run_cli(["sfm", "--images", photos, "--out", tmp_path / "proj2"], capsys)
    assert code == 0 and not _warnings(err), err  # every photo registered: nothing to say


@pytest.mark.parametrize("value", ["1.5", "-0.1", "nan"])
def test_sfm_min_registered_outside_0_1_is_refused_before_any_work(photos, tmp_path, capsys, monkeypatch, value):
    fake = _fake(monkeypatch, 10)
    code, _, err = run_cli(["sfm", "--images", photos, "--out", tmp_path / "proj", "--min-registered", value],
                           capsys)
    assert "--min-registered must be the least share" in _one_error(code, err), err
    assert fake.maps == 0 and not (tmp_path / "proj").exists()


def test_train_refuses_a_folder_sfm_mostly_dropped_and_the_flag_accepts_it(photos, tmp_path, capsys, monkeypatch):
    _fake(monkeypatch, 3)
    run = tmp_path / "run"
    code, _, err = run_cli(["train", "--data", photos, "--out", run, "--device", "cpu", "--set", "steps=1"], capsys)
    line = _one_error(code, err)
    assert "registered only 3 of 10 photos" in line and "--min-registered 0.3" in line, line
    assert not run.exists()
    code, _, err = run_cli(["train", "--data", photos, "--out", run, "--device", "cpu", "--set", "steps=1",
                            "--set", "decomposer.method=none", "--min-registered", "0.3"], capsys)
    assert code == 0, err
    assert any("SfM registered 3 of 10 photos" in ln for ln in _warnings(err)), err
    recorded = yaml.safe_load((run / "config.yaml").read_text())
    assert recorded["data"]["min_registered"] == 0.3  # eval and render read the scene as training did
    code, _, err = run_cli(["eval", "--run", run, "--device", "cpu"], capsys)
    assert code == 0, err


def test_train_min_registered_out_of_range_is_one_line(photos, tmp_path, capsys, monkeypatch):
    fake = _fake(monkeypatch, 10)
    code, _, err = run_cli(["train", "--data", photos, "--out", tmp_path / "run", "--device", "cpu",
                            "--min-registered", "2"], capsys)
    assert "data.min_registered" in _one_error(code, err), err
    assert fake.maps == 0


def test_the_default_share_is_the_configs_and_older_runs_accept_any_model(tmp_path):
    from retinexgs.data.sfm import MIN_REGISTERED_SHARE
    from retinexgs.config import configs_dir, plain
    from retinexgs.run.config import load_config
    from retinexgs.run.folder import read_run_config

    default = yaml.safe_load((configs_dir() / "default.yaml").read_text())
    assert default["data"]["min_registered"] == MIN_REGISTERED_SHARE == 0.5
    old = plain(load_config())
    del old["data"]["min_registered"]  # a run made before the key: it trained on whatever SfM registered
    old["scene"] = str(tmp_path)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(old))
    cfg, _ = read_run_config(tmp_path)
    assert cfg.data.min_registered == 0.0


# ---- item 3: raw files of two sizes, before SfM --------------------------------------------------------------

def _dng(path: Path, w: int, h: int, seed: int) -> None:
    from retinexgs.data.dng import write_dng

    path.parent.mkdir(parents=True, exist_ok=True)
    mosaic = np.random.default_rng(seed).integers(500, 4000, (h, w)).astype(np.uint16)
    write_dng(path, mosaic, white_level=4095, exposure_time=0.1, iso=100, f_number=2.8)


def test_raw_files_of_two_sizes_are_refused_before_sfm(tmp_path, capsys, monkeypatch):
    # SfM posed only one size's photos, so the loader's size check (on the registered views) never saw the other
    folder = tmp_path / "night"
    for i in range(4):
        _dng(folder / f"a{i}.dng", 64, 48, i)
    for i in range(3):
        _dng(folder / f"b{i}.dng", 48, 36, 10 + i)
    fake = _fake(monkeypatch, 4)
    code, _, err = run_cli(["sfm", "--images", folder, "--out", tmp_path / "proj"], capsys)
    line = _one_error(code, err)
    assert "holds raw photos of different sizes: a0.dng is 64x48, b0.dng 48x36" in line, line
    code, _, err = run_cli(["train", "--data", folder, "--out", tmp_path / "run", "--device", "cpu"], capsys)
    assert "different sizes" in _one_error(code, err), err
    assert fake.maps == 0 and not (tmp_path / "proj").exists() and not (folder / "retinexgs_sfm").exists()


def test_raw_plus_jpeg_pairs_of_two_raw_sizes_are_refused_before_sfm(tmp_path, monkeypatch):
    from retinexgs.data.sfm import run_sfm

    folder = tmp_path / "capture"
    for i, (w, h) in enumerate([(64, 48), (64, 48), (48, 36)]):
        _dng(folder / f"c{i}.dng", w, h, i)
        _photo(folder / f"c{i}.jpg", i)
    fake = _fake(monkeypatch, 3)
    with pytest.raises(UserError, match=r"different sizes: c0\.dng is 64x48, c2\.dng 48x36"):
        run_sfm(folder, tmp_path / "proj", progress=None)
    assert fake.maps == 0
