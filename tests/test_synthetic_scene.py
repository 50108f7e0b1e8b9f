"""The synthetic dark demo scene: files, darkness, noise, camera convention, determinism."""
import hashlib
import json
import math

import numpy as np
import pytest
from PIL import Image

from retinexgs.demo.synthetic import SPHERES, cast_rays, demo_cameras, make_demo_scene

ARGS = dict(n_train=5, n_test=2, width=48, height=36, seed=3, n_points=600)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("demo") / "scene", **ARGS)


def _cameras() -> dict:
    """The ground-truth cameras of the fixture's scene, by file name."""
    keys = ("n_train", "n_test", "width", "height", "seed")
    return {c.name: c for c in demo_cameras(**{k: ARGS[k] for k in keys})}


def _img(path) -> np.ndarray:
    return np.asarray(Image.open(path), dtype=np.float64) / 255.0


def _json_project(meta: dict, frame: dict, p: np.ndarray) -> np.ndarray:
    """Project world points [N,3] with a transforms-JSON frame: OpenGL camera-to-world, pixel-centre cx/cy."""
    c2w = np.asarray(frame["transform_matrix"], np.float64)
    cam = (p - c2w[:3, 3]) @ c2w[:3, :3]  # world -> camera (x right, y up, z back)
    depth = -cam[:, 2]
    u = meta["fl_x"] * cam[:, 0] / depth + meta["cx"]
    v = meta["cy"] - meta["fl_y"] * cam[:, 1] / depth
    return np.stack([u, v, depth], -1)


def test_files_and_json(scene):
    names = sorted(p.name for p in (scene / "low").iterdir())
    assert names == sorted(p.name for p in (scene / "high").iterdir())
    assert len(names) == 7
    train = json.loads((scene / "transforms_train.json").read_text())
    test = json.loads((scene / "transforms_test.json").read_text())
    assert len(train["frames"]) == 5 and len(test["frames"]) == 2
    assert all(f["file_path"].startswith("low/") for f in train["frames"])
    assert all(f["file_path"].startswith("high/") for f in test["frames"])
    listed = sorted(f["file_path"].split("/")[1] for f in train["frames"] + test["frames"])
    assert listed == names
    for meta in (train, test):
        assert (meta["w"], meta["h"]) == (48, 36)
        assert meta["cx"] == 24.0 and meta["cy"] == 18.0
        assert meta["fl_x"] == pytest.approx(0.5 * 48 / math.tan(meta["camera_angle_x"] / 2))
        for f in meta["frames"]:
            m = np.asarray(f["transform_matrix"])
            assert m.shape == (4, 4)
            assert np.allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-9)
            assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0)
            assert np.allclose(m[3], [0, 0, 0, 1])
    for n in names:
        assert _img(scene / "low" / n).shape == (36, 48, 3)
    pts = np.load(scene / "points3d.npy")
    assert pts.shape == (600, 6) and pts.dtype == np.float32
    assert (pts[:, 3:] >= 0).all() and (pts[:, 3:] <= 1).all()
    for f in ("cameras.txt", "images.txt", "points3D.txt"):
        assert (scene / "colmap_sparse" / "0" / f).is_file()
    split = json.loads((scene / "split.json").read_text())
    assert sorted(split["train"] + split["test"]) == names


def test_low_is_dark_and_noisy(scene, tmp_path):
    names = sorted(p.name for p in (scene / "low").iterdir())
    low = np.stack([_img(scene / "low" / n) for n in names])
    high = np.stack([_img(scene / "high" / n) for n in names])
    assert low.mean() / high.mean() < 0.2
    assert high.mean() > 0.25  # the normal-light images are not themselves dark
    # Noise: the same first view without shot/read noise (its darkening draws come first, so they match).
    clean = make_demo_scene(tmp_path / "clean", **ARGS, full_well=1e12, read_noise=0.0)
    a, b = _img(scene / "low" / names[0]), _img(clean / "low" / names[0])
    assert abs(a.mean() - b.mean()) < 0.01
    assert (a - b).std() > 3 / 255
    assert np.array_equal(_img(scene / "high" / names[0]), _img(clean / "high" / names[0]))


def test_pixel_rays_match_json_projection(scene):
    train = json.loads((scene / "transforms_train.json").read_text())
    test = json.loads((scene / "transforms_test.json").read_text())
    by_name = _cameras()
    rows, cols = np.meshgrid(np.arange(0, 36, 5), np.arange(0, 48, 7), indexing="ij")
    for meta in (train, test):
        for frame in meta["frames"]:
            cam = by_name[frame["file_path"].split("/")[1]]
            assert np.allclose(cam.c2w_gl, frame["transform_matrix"])
            o, d = cam.pixel_rays()  # pixel centres
            hit = cast_rays(o[0, rows, cols], d[0, rows, cols])
            ok = np.isfinite(hit["t"])
            assert ok.mean() > 0.5
            uvz = _json_project(meta, frame, hit["point"][ok])
            assert np.allclose(uvz[:, 0], cols[ok] + 0.5, atol=1e-6)
            assert np.allclose(uvz[:, 1], rows[ok] + 0.5, atol=1e-6)
            assert np.allclose(uvz[:, 2], hit["t"][ok] * (d[0, rows, cols][ok] @ -cam.c2w_gl[:3, 2]), atol=1e-6)


def test_known_point_lands_on_its_object(scene):
    """The front point of each sphere, projected with the JSON pose, is hit by the ray through that pixel."""
    meta = json.loads((scene / "transforms_train.json").read_text())
    by_name = _cameras()
    hits = total = 0
    for frame in meta["frames"]:
        cam = by_name[frame["file_path"].split("/")[1]]
        for s, (c, r, _) in enumerate(SPHERES):
            c = np.asarray(c)
            to_cam = cam.center - c
            p = c + r * to_cam / np.linalg.norm(to_cam)
            u, v, _ = _json_project(meta, frame, p[None])[0]
            if not (0 <= u < 48 and 0 <= v < 36):
                continue
            o, d = cam.pixel_rays()
            i, j = int(v), int(u)
            total += 1
            hit = cast_rays(o[0, i, j], d[0, i, j])
            hits += int(hit["obj"] == s + 1) or int(np.linalg.norm(hit["point"] - p) < 0.05)
    assert total >= 10 and hits >= 0.8 * total, (hits, total)  # the rest are occluded by another object


def test_loader_reads_the_scene(scene):
    data = pytest.importorskip("retinexgs.data")
    torch = pytest.importorskip("torch")
    s = data.load_scene(scene, normalize=False)
    assert len(s.train) == 5 and len(s.test) == 2
    assert s.points_source == "colmap"
    assert np.allclose(s.points.numpy(), np.load(scene / "points3d.npy")[:, :3], atol=1e-5)
    by_name = _cameras()
    for v in s.train + s.test:
        cam = by_name[v.name]
        assert v.paired_image is not None
        o, d = cam.pixel_rays()
        hit = cast_rays(o[0, 20, 30], d[0, 20, 30])
        uvz = v.project(torch.tensor(hit["point"][None]))
        assert np.allclose(uvz[0, :2].numpy(), [30.5, 20.5], atol=1e-6)
    # The COLMAP text model holds the same poses (as world-to-camera quaternions).
    sc = data.load_scene(scene, reader="colmap", normalize=False)
    json_poses = {v.name: v.camera_to_world.numpy() for v in s.views}
    for v in sc.views:
        assert np.allclose(v.camera_to_world.numpy(), json_poses[v.name], atol=1e-9)


def _digest(root) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_deterministic_for_a_seed(scene, tmp_path):
    again = make_demo_scene(tmp_path / "again", **ARGS)
    assert _digest(again) == _digest(scene)
    other = make_demo_scene(tmp_path / "other", **{**ARGS, "seed": 4})
    assert not np.array_equal(_img(other / "low" / "0000.png"), _img(scene / "low" / "0000.png"))
