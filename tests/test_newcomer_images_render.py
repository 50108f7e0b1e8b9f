"""Issue 50, a newcomer's third hour: phone photos (HEIC/HEIF) read like JPEGs and train; ``render``'s --out
(views into a folder, a path video into a folder or a .mp4), its L map normalised as ``eval`` shows it, the orbit
of a front-facing capture kept within the cameras' spread, and the exported PLY's comment naming the run's tone."""
import json
import math
from pathlib import Path

import numpy as np
import pillow_heif  # an install requirement (setup.py), as Pillow is
import pytest
import torch
from PIL import Image

from retinexgs.cli import main
from retinexgs.data import images
from retinexgs.data.scene import View
from scenes import TINY_RUN, run_cli, tiny_trained_run

ORIENTATION = 0x0112  # the EXIF tag


def smooth_image(h=48, w=64):
    """A smooth colour picture with a few edges: a lossy codec keeps it within a few levels."""
    y, x = np.mgrid[0:h, 0:w]
    rgb = np.stack([x / (w - 1), y / (h - 1), 0.5 + 0.3 * np.sin(x / 7.0)], -1)
    rgb[: h // 3, : w // 4] = [0.9, 0.2, 0.1]  # a block that is only in the top-left corner
    return (rgb * 255 + 0.5).astype(np.uint8)


def save_heic(rgb, path, orientation=None):
    pillow_heif.register_heif_opener()
    kwargs = {}
    if orientation is not None:
        exif = Image.Exif()
        exif[ORIENTATION] = orientation
        kwargs["exif"] = exif.tobytes()
    Image.fromarray(rgb).save(path, format="HEIF", quality=95, **kwargs)
    return path


# ---- HEIC / HEIF ----------------------------------------------------------------------------------------------

def test_heic_reads_as_the_png_does_and_ignores_orientation_as_for_jpeg(tmp_path):
    rgb = smooth_image()
    Image.fromarray(rgb).save(tmp_path / "a.png")
    save_heic(rgb, tmp_path / "a.HEIC")
    png = images.read_image(tmp_path / "a.png")
    heic = images.read_image(tmp_path / "a.HEIC")
    assert heic.shape == png.shape == (48, 64, 3)
    assert np.abs(heic.astype(int) - png.astype(int)).mean() < 4.0  # HEVC at quality 95
    # EXIF orientation 6 ("turn 90° to view"): the JPEG reads as stored, and so does the HEIC, which the decoder
    # would otherwise turn upright (64x48 stored -> 48x64 shown)
    exif = Image.Exif()
    exif[ORIENTATION] = 6
    Image.fromarray(rgb).save(tmp_path / "b.jpg", quality=95, exif=exif.tobytes())
    for name in ("b.jpg", "b.heic"):
        if name.endswith("heic"):
            save_heic(rgb, tmp_path / name, orientation=6)
            with Image.open(tmp_path / name) as im:  # the decoder did turn it: the case this guards
                assert im.size == (48, 64) and im.info.get("original_orientation") == 6
        got = images.read_image(tmp_path / name)
        assert got.shape == (48, 64, 3), name
        assert images.image_size(tmp_path / name) == (64, 48), name
        assert np.abs(got.astype(int) - png.astype(int)).mean() < 4.0, name
        assert got[2, 2, 1] < 100 and got[-2, -2, 1] > 200, name  # the red block stays top-left


def test_heic_and_heif_are_listed_in_any_case(tmp_path):
    rgb = smooth_image(16, 16)
    for name in ("a.HEIC", "b.heif", "c.Heic", "d.JPG"):
        if name.lower().endswith((".heic", ".heif")):
            save_heic(rgb, tmp_path / name)
        else:
            Image.fromarray(rgb).save(tmp_path / name, format="JPEG")
    (tmp_path / "notes.txt").write_text("not a photo")
    assert [p.name for p in images.list_images(tmp_path)] == ["a.HEIC", "b.heif", "c.Heic", "d.JPG"]
    from retinexgs.retinex import cache
    assert cache.IMAGE_EXTENSIONS is images.IMAGE_EXTENSIONS  # one list, used everywhere


def test_a_folder_without_readable_photos_names_the_readable_formats(tmp_path, capsys):
    # Sigma .X3F (Foveon): a raw type that is not read (camera raws LibRaw reads as Bayer are: tests/test_raw_scenes.py)
    scene = tmp_path / "raw_photos"
    scene.mkdir()
    for i in range(3):
        (scene / f"IMG_{i}.X3F").write_bytes(b"raw sensor data")
    code, _, err = run_cli(["train", "--data", scene, "--out", tmp_path / "run", "--device", "cpu", "--quiet"],
                           capsys)
    assert code == 2 and "Traceback" not in err
    assert ".heic" in err and ".jpg" in err and ".dng" in err and ".x3f" in err
    assert not (tmp_path / "run").exists()


def test_sfm_sees_heic_photos_and_its_feature_copies_read_them(tmp_path):
    """sfm lists photos through images.list_images and writes its brightened copies for COLMAP from
    images.read_image, under the photo's own name: both work for HEIC, and a copy reads back (PNG bytes, which
    COLMAP reads whatever the name says)."""
    from retinexgs.data.enhance import enhance_for_features, folder_is_dark

    folder = tmp_path / "phone"
    folder.mkdir()
    dark = (smooth_image() * 0.08).astype(np.uint8)
    for i in range(3):
        save_heic(np.roll(dark, 3 * i, axis=1), folder / f"IMG_{i:04d}.HEIC")
    paths = images.list_images(folder)
    assert len(paths) == 3 and folder_is_dark(paths)
    dst = tmp_path / "enhanced" / paths[0].name
    images.write_image_atomic(dst, enhance_for_features(images.read_image(paths[0])), quality=97)
    back = images.read_image(dst)
    assert back.shape == (48, 64, 3) and back.mean() > images.read_image(paths[0]).mean()
    with open(dst, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"


def test_a_heic_scene_loads_and_trains_through_the_cli(tmp_path, capsys):
    """A LOM-style scene (low/, high/, transforms JSON) whose photos are all HEIC: `train` reads, trains, writes."""
    from retinexgs.demo.synthetic import make_demo_scene

    scene = make_demo_scene(tmp_path / "scene", n_train=3, n_test=1, width=24, height=18, n_points=200)
    for folder in ("low", "high"):
        for png in sorted((scene / folder).glob("*.png")):
            save_heic(np.asarray(Image.open(png).convert("RGB")), png.with_suffix(".HEIC"))
            png.unlink()
    for split in ("train", "test"):
        path = scene / f"transforms_{split}.json"
        data = json.loads(path.read_text())
        for frame in data["frames"]:
            frame["file_path"] = str(Path(frame["file_path"]).with_suffix(".HEIC"))
        path.write_text(json.dumps(data))
    sets = [a for s in TINY_RUN for a in ("--set", s)]
    code, _, err = run_cli(["train", "--data", scene, "--out", tmp_path / "run", "--config", "demo", *sets,
                            "--device", "cpu", "--quiet"], capsys)
    assert code == 0, err
    assert (tmp_path / "run" / "metrics.json").is_file()
    assert any((tmp_path / "run" / "checkpoints").iterdir())


# ---- render / export on a tiny run ---------------------------------------------------------------------------

TINY = TINY_RUN + ["eval.lpips=false"]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    _, run = tiny_trained_run(tmp_path_factory.mktemp("newcomer"), TINY, n_test=2, width=32, height=24)
    return run


def cli(*args):
    return main([*map(str, args), "--device", "cpu", "--quiet"])


def test_views_into_an_mp4_name_are_refused_before_anything_is_written(run_dir, tmp_path, capsys):
    code, _, err = run_cli(["render", "--run", run_dir, "--out", tmp_path / "x.mp4", "--device", "cpu", "--quiet"],
                           capsys)
    assert code == 2 and "Traceback" not in err
    assert "x.mp4" in err and "folder" in err and "--path" in err
    assert not (tmp_path / "x.mp4").exists()
    code, _, err = run_cli(["render", "--run", run_dir, "--path", "orbit", "--format", "png", "--out",
                            tmp_path / "y.MP4", "--device", "cpu", "--quiet"], capsys)
    assert code == 2 and "folder" in err and not (tmp_path / "y.MP4").exists()


def test_a_path_video_goes_into_a_folder_or_to_the_mp4_named(run_dir, tmp_path, capsys):
    assert cli("render", "--run", run_dir, "--path", "orbit", "--frames", 2, "--out", tmp_path / "videos") == 0
    assert sorted(p.name for p in (tmp_path / "videos").iterdir()) == ["path_orbit.mp4"]
    (tmp_path / "mine").mkdir()
    assert cli("render", "--run", run_dir, "--path", "interpolate", "--frames", 2, "--maps", "enhanced,depth",
               "--out", tmp_path / "mine") == 0
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["path_interpolate.mp4",
                                                                      "path_interpolate_depth.mp4"]
    assert cli("render", "--run", run_dir, "--path", "orbit", "--frames", 2, "--out", tmp_path / "clip.mp4") == 0
    assert (tmp_path / "clip.mp4").is_file()
    code, _, err = run_cli(["render", "--run", run_dir, "--path", "orbit", "--out", tmp_path / "clip.mov",
                            "--device", "cpu", "--quiet"], capsys)
    assert code == 2 and "MP4" in err and not (tmp_path / "clip.mov").exists()


def test_render_L_is_normalised_as_eval_shows_it_and_L_raw_is_as_rendered(run_dir, tmp_path):
    from retinexgs.evaluate.evaluate import LABEL_ROWS
    from retinexgs.run.folder import load_run

    assert cli("render", "--run", run_dir, "--out", tmp_path / "maps", "--maps", "L,L_raw") == 0
    assert cli("eval", "--run", run_dir) == 0
    _, _, model, _ = load_run(run_dir, "cpu")
    ref = float(model.illum_ref)
    names = sorted(p.name for p in (tmp_path / "maps" / "L").iterdir())
    assert len(names) == 2
    for name in names:
        L = np.asarray(Image.open(tmp_path / "maps" / "L" / name), float)
        raw = np.asarray(Image.open(tmp_path / "maps" / "L_raw" / name), float)
        # L = clip(L̂ / L_ref): the raw map scaled by one scene-wide constant (within the two 8-bit roundings)
        assert np.abs(L - np.clip(raw / ref, 0, 255)).max() <= 1.0 / ref + 1.0
        assert L.mean() > raw.mean() + 1.0  # a dark capture's L̂ brightened
        side = np.asarray(Image.open(run_dir / "renders" / "test" / name))[LABEL_ROWS:]
        w = L.shape[1]
        assert np.abs(side[:, 3 * w:4 * w].astype(float) - L).max() <= 1.0  # eval's L panel: the same picture


def _view(eye, target, up=(0.0, -1.0, 0.0), w=32, h=24):
    from retinexgs.export.paths import look_at

    c2w = look_at(np.asarray(eye, float), np.asarray(target, float), -np.asarray(up, float))
    return View("v", Path(), 30.0, 30.0, w / 2, h / 2, w, h, torch.from_numpy(c2w))


def test_orbit_of_a_front_facing_capture_stays_within_the_cameras_spread():
    from retinexgs.export.paths import camera_path, is_front_facing

    # LLFF-like: a 3x3 grid of cameras 0.6 wide, 0.4 high, all looking at a point 4 ahead
    target = np.array([0.0, 0.0, 4.0])
    views = [_view((x, y, 0.05 * x), target) for x in (-0.3, 0.0, 0.3) for y in (-0.2, 0.0, 0.2)]
    points = torch.from_numpy(target + np.random.default_rng(0).normal(0, 0.5, (200, 3)))  # the scene's Gaussians
    assert is_front_facing(views)
    path = camera_path("orbit", views, 16, points)
    centres = np.stack([v.camera_center.numpy() for v in views])
    lo, hi = centres.min(0) - 1e-3, centres.max(0) + 1e-3  # a thousandth of the scene: the plane tilts a little
    dirs = np.stack([v.camera_to_world[:3, 2].numpy() for v in views])
    for frame in path:
        c = frame.camera_center.numpy()
        assert np.all(c >= lo) and np.all(c <= hi)  # never beyond where a camera stood
        d = frame.camera_to_world[:3, 2].numpy()
        assert (dirs @ d).max() > math.cos(math.radians(10))  # looks the way the cameras looked
    spread = np.ptp(np.stack([f.camera_center.numpy() for f in path]), axis=0)
    assert spread[0] > 0.4 and spread[1] > 0.25  # it does move: an ellipse over the spread
    # the full circle on request: half of it behind the scene, where no camera was
    full = camera_path("orbit-360", views, 16, points)
    assert sum(f.camera_center.numpy()[2] > 4.0 for f in full) >= 6


def test_orbit_of_a_capture_around_the_scene_is_the_full_circle():
    from retinexgs.export.paths import camera_path, is_front_facing

    views = [_view((3 * math.sin(a), -1.0, 3 * math.cos(a)), (0, 0, 0))
             for a in np.radians([0, 50, 130, 200, 290])]
    assert not is_front_facing(views)
    orbit, full = camera_path("orbit", views, 12), camera_path("orbit-360", views, 12)
    for a, b in zip(orbit, full):
        assert torch.allclose(a.camera_to_world, b.camera_to_world)
    radii = [np.linalg.norm(f.camera_center.numpy()) for f in orbit]  # around the point all cameras look at
    assert np.ptp(radii) < 1e-6 and min(radii) > 2.5


def test_exported_ply_comment_states_the_runs_tone(run_dir, tmp_path):
    import plyfile

    from retinexgs.export.bake import baked_colour_text
    from retinexgs.run.folder import load_run

    out = tmp_path / "scene.ply"
    assert cli("export", "--run", run_dir, "--out", out) == 0
    comments = " ".join(plyfile.PlyData.read(str(out)).comments)
    _, _, model, _ = load_run(run_dir, "cpu")
    assert model.tone.name == "exposure"  # the default tone: the comment describes a gain, not a gamma on L
    assert "srgb(" in comments and "k = lin(L_ref)^(-1/g)" in comments and "(L/L_ref)^g" not in comments
    g = torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)
    model.tone = "illumination"
    assert "R*clip(L/L_ref,0,1)^g" in baked_colour_text(model, g, 64)
    model.tone = "signal"
    assert "R^g*clip(L/L_ref,0,1)^g" in baked_colour_text(model, g, 64)


def test_sfm_on_a_bright_heic_folder_extracts_features_from_decoded_copies(tmp_path, monkeypatch):
    """A folder of HEIC photos that is not dark: COLMAP cannot decode HEIC, so sfm writes plain decoded copies (PNG
    bytes under the photos' own names, not brightened), extracts features from them and maps from them. Full SfM
    on synthetic views may not register, so the mapper is replaced by one that records what it was given."""
    import pycolmap

    from retinexgs.data import sfm
    from retinexgs.errors import UserError

    folder = tmp_path / "phone"
    folder.mkdir()
    rng = np.random.default_rng(0)
    base = (rng.random((96, 128, 3)) * 255).astype(np.uint8)  # texture: features to find
    for i in range(3):
        save_heic(np.roll(base, 4 * i, axis=1), folder / f"IMG_{i:04d}.HEIC")
    seen = {}

    def mapper(db, image_path, out, **kwargs):
        seen["image_path"] = Path(image_path)
        database = pycolmap.Database.open(str(db))
        seen["keypoints"] = {im.name: database.num_keypoints_for_image(im.image_id)
                             for im in database.read_all_images()}
        database.close()
        copy = Path(image_path) / "IMG_0000.HEIC"  # read now: a failed sfm removes what it made
        seen["magic"], seen["copy"] = copy.read_bytes()[:8], np.asarray(Image.open(copy).convert("RGB"))
        return {}

    monkeypatch.setattr(pycolmap, "incremental_mapping", mapper)
    with pytest.raises(UserError, match="could not build a model"):
        sfm.run_sfm(folder, tmp_path / "sfm", progress=None)
    assert seen["image_path"] == tmp_path / "sfm" / "enhanced"
    assert sorted(seen["keypoints"]) == [f"IMG_{i:04d}.HEIC" for i in range(3)]
    assert min(seen["keypoints"].values()) > 0, seen["keypoints"]
    assert seen["magic"] == b"\x89PNG\r\n\x1a\n"
    # decoded, not brightened: the copy is the photo
    assert np.abs(seen["copy"].astype(int) - images.read_image(folder / "IMG_0000.HEIC").astype(int)).max() == 0
