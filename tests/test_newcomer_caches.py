"""Issue 50 ("A newcomer's third hour"), the caches and the decomposer's parameters: the image cache and the view
store are keyed by content (item 3), decomposer.params is checked by the schema before anything loads (item 5), the
cache keeps what another resolution or scene uses (item 6), and decompose's full-disk message names --cache (9)."""
from __future__ import annotations

import dataclasses
import errno
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from retinexgs.data import load_scene
from retinexgs.data.images import read_image, resize_image
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.retinex.lime import LIMEParams
from retinexgs.retinex.lr3m import LR3MParams
from retinexgs.config.schema import LIMEParamsSchema, LR3MParamsSchema
from retinexgs.train.view_store import store_fingerprint
from scenes import run_cli

W, H = 40, 32  # downscale 2 -> 20x16, above the 11 px minimum


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("demo") / "scene", n_train=3, n_test=1, width=W, height=H,
                           n_points=200)


def _copy(demo: Path, dst: Path, gain: float = 1.0) -> Path:
    """A copy of the demo scene; with ``gain`` != 1 every low/ photo is re-exposed (same names, other pixels)."""
    shutil.copytree(demo, dst)
    if gain != 1.0:
        for p in sorted((dst / "low").iterdir()):
            a = np.asarray(Image.open(p).convert("RGB")).astype(np.float32)
            Image.fromarray(np.clip(a * gain + 3, 0, 255).astype(np.uint8)).save(p)
    return dst


def _expected(src: Path) -> np.ndarray:
    """What the cache must hold for ``src`` at downscale 2 (the demo's camera has no distortion)."""
    return resize_image(read_image(src), W // 2, H // 2)


# ---- item 3: the image cache is keyed by content ----------------------------------------------------------------

def _assert_views_hold(scene, root: Path) -> None:
    """Every view of ``scene`` reads a cached copy made from its own photo under ``root``."""
    views = scene.train + scene.test
    assert len(views) == 4
    for v in views:
        assert v.image_path != v.source_path and Path(v.source_path).resolve().parent == (root / "low").resolve()
        assert np.array_equal(read_image(v.image_path), _expected(v.source_path)), (v.image_path, v.source_path)


def test_two_scenes_sharing_a_cache_dir_get_their_own_pixels(demo, tmp_path):
    d1 = _copy(demo, tmp_path / "d1")
    d2 = _copy(demo, tmp_path / "d2", gain=2.5)  # the same file names, other pixels
    cache = tmp_path / "C"
    s2 = load_scene(d2, downscale=2, cache_dir=cache)
    s1 = load_scene(d1, downscale=2, cache_dir=cache)  # before: d2's copies, newer than d1's photos, were reused
    _assert_views_hold(s2, d2)
    _assert_views_hold(s1, d1)
    assert {v.image_path for v in s1.train}.isdisjoint(v.image_path for v in s2.train)
    # and back: d2's copies are still there, nothing recomputed or mixed up
    before = {p: p.stat().st_mtime_ns for p in cache.rglob("*.png")}
    _assert_views_hold(load_scene(d2, downscale=2, cache_dir=cache), d2)
    assert {p: p.stat().st_mtime_ns for p in cache.rglob("*.png")} == before


def test_a_photo_replaced_with_an_older_mtime_is_processed_again(demo, tmp_path):
    scene = _copy(demo, tmp_path / "s")
    other = _copy(demo, tmp_path / "other", gain=0.5)
    load_scene(scene, downscale=2)  # fills scene/retinexgs_cache
    photo = sorted((scene / "low").iterdir())[0]
    shutil.copy2(other / "low" / photo.name, photo)  # as `cp -p`: other bytes ...
    os.utime(photo, ns=(1_000_000_000, 1_000_000_000))  # ... and a modification time older than the cache
    _assert_views_hold(load_scene(scene, downscale=2), scene)


def test_the_view_store_key_follows_the_content_not_the_mtime(demo, tmp_path):
    scene = _copy(demo, tmp_path / "s")
    paths = sorted((scene / "low").iterdir())
    sizes = [(H, W)] * len(paths)
    before = store_fingerprint(paths, sizes, "none")
    st = paths[0].stat()
    img = np.asarray(Image.open(paths[0]).convert("RGB")).copy()
    img[0, 0] = 255 - img[0, 0]
    tmp = tmp_path / "new.png"
    Image.fromarray(img).save(tmp)
    tmp.replace(paths[0])
    os.utime(paths[0], ns=(st.st_atime_ns, st.st_mtime_ns))  # the same mtime as before
    after = store_fingerprint(paths, sizes, "none")
    assert after != before
    os.utime(paths[0], ns=(1, 1))  # only the mtime changes: the same store
    assert store_fingerprint(paths, sizes, "none") == after
    moved = _copy(scene, tmp_path / "moved")  # the same bytes elsewhere: the same key
    assert store_fingerprint(sorted((moved / "low").iterdir()), sizes, "none") == after


# ---- item 5: decomposer.params are checked by the schema, before the scene loads ---------------------------------

@pytest.mark.parametrize("setting, expect", [
    ("decomposer.params.foo=1", "unknown config key decomposer.params.foo: lr3m has no parameter 'foo' "
                                "(its parameters: beta, omega, "),
    ("decomposer.params.iterations=abc", "decomposer.params.iterations must be an integer >= 1, got 'abc'"),
    ("decomposer.params.iterations=-1", "decomposer.params.iterations must be an integer >= 1, got -1"),
    ("decomposer.params.iterations=2.5", "decomposer.params.iterations must be an integer >= 1, got 2.5"),
    ("decomposer.params.beta=-0.1", "decomposer.params.beta must be a number >= 0, got -0.1"),
    ("decomposer.params.solver=qr", "decomposer.params.solver must be one of gram, svd, got 'qr'"),
    ("decomposer.params.median_guide=1", "decomposer.params.median_guide must be true or false, got 1"),
    ("decomposer.params.tile_margin=50", "lr3m's tile_margin (50) must be a multiple of stride (6)"),
])
@pytest.mark.parametrize("command", ["decompose", "train"])
def test_bad_decomposer_params_are_one_line_before_the_scene_loads(tmp_path, capsys, monkeypatch, setting, expect,
                                                                    command):
    import retinexgs.data.load as load_mod

    def no_loading(*a, **k):  # the check comes before any scene is read
        raise AssertionError("the scene was loaded before the config was checked")

    monkeypatch.setattr(load_mod, "load_scene", no_loading)
    scene = tmp_path / "scene"
    (scene / "low").mkdir(parents=True)
    Image.fromarray(np.full((16, 16, 3), 40, np.uint8)).save(scene / "low" / "a.png")
    argv = ["decompose", "--data", scene, "--quiet"] if command == "decompose" else \
        ["train", "--data", scene, "--out", tmp_path / "run", "--device", "cpu"]
    code, out, err = run_cli(argv + ["--set", setting], capsys)
    assert code == 2, (code, out, err)
    assert f"--set {setting}: " in err and expect in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in scene.iterdir()) == ["low"]  # nothing written


def test_lime_params_are_checked_as_lime_and_good_values_pass(tmp_path, capsys):
    from retinexgs.run.config import load_config

    cfg = load_config(overrides=["decomposer.method=lime", "decomposer.params={alpha: 0.3, cg_max_iter: 50}"])
    assert cfg.decomposer.params == {"alpha": 0.3, "cg_max_iter": 50}
    assert load_config(overrides=["decomposer.params.beta=1"]).decomposer.params == {"beta": 1.0}
    from retinexgs.errors import UserError
    with pytest.raises(UserError, match="lime has no parameter 'iterations'"):
        load_config(overrides=["decomposer.method=lime", "decomposer.params.iterations=3"])
    # method none reads no parameters: nothing to check
    assert load_config(overrides=["decomposer.method=none"]).decomposer.params == {}


def test_every_decomposer_parameter_has_a_schema_field():
    for params, schema in ((LR3MParams, LR3MParamsSchema), (LIMEParams, LIMEParamsSchema)):
        assert [f.name for f in dataclasses.fields(params)] == list(schema.model_fields), params
        # the published defaults pass their own schema
        from retinexgs.config.schema import check_decomposer_params
        method = "lr3m" if params is LR3MParams else "lime"
        assert check_decomposer_params(method, dataclasses.asdict(params())) == dataclasses.asdict(params())


def test_denoise_params_schema_matches_the_denoiser_and_reaches_it(tmp_path):
    """decomposer.denoise_params: the schema names DenoiseParams' fields, bad keys and values give one line, and the
    overrides add up key by key like decomposer.params and reach the denoiser's spec (its cache key with them)."""
    from retinexgs.config.schema import DenoiseParamsSchema, check_decomposer_params
    from retinexgs.errors import UserError
    from retinexgs.retinex.denoise import DenoiseParams, NoiseModel, denoise_key
    from retinexgs.run.config import load_config

    assert [f.name for f in dataclasses.fields(DenoiseParams)] == list(DenoiseParamsSchema.model_fields)
    defaults = dataclasses.asdict(DenoiseParams())
    assert check_decomposer_params("denoise", defaults, "decomposer.denoise_params") == defaults
    cfg = load_config(overrides=["decomposer.denoise_params.h_luma=0.4", "decomposer.denoise_params.radius=12"])
    assert cfg.decomposer.denoise_params == {"h_luma": 0.4, "radius": 12}
    assert load_config(overrides=["decomposer.denoise_params={}"]).decomposer.denoise_params == {}
    assert load_config(["configs/ablations/denoise_luma_0.4.yaml"]).decomposer.denoise_params == {"h_luma": 0.4}
    for bad, message in (("decomposer.denoise_params.foo=1", "denoise has no parameter 'foo'"),
                         ("decomposer.denoise_params.h_luma=-1", "h_luma must be a number >= 0"),
                         ("decomposer.denoise_params.calibrate=3", "calibrate must be true or false")):
        with pytest.raises(UserError, match=message):
            load_config(overrides=[bad])
    p = DenoiseParams.from_mapping(cfg.decomposer.denoise_params)
    assert (p.h_luma, p.radius, p.h_chroma) == (0.4, 12, DenoiseParams().h_chroma)
    noise = NoiseModel((1e-3,) * 3, (1e-5,) * 3)
    assert denoise_key("chroma", noise, p) != denoise_key("chroma", noise)


# ---- item 6: the cache keeps what another resolution or scene uses --------------------------------------------------

def _decompose(capsys, scene: Path, *extra) -> str:
    code, out, err = run_cli(["decompose", "--data", scene, "--method", "lime", "--quiet", "--device", "cpu",
                              *extra], capsys)
    assert code == 0, err
    return out


def test_another_resolution_or_scene_does_not_delete_the_entries(demo, tmp_path, capsys):
    a = _copy(demo, tmp_path / "a")
    out = _decompose(capsys, a)
    assert "3 computed" in out and "deleted" not in out, out
    out = _decompose(capsys, a, "--set", "data.downscale=2")
    assert "3 computed" in out and "deleted" not in out, out
    assert "also holds 3 entries" in out and "--prune" in out, out  # the other resolution's, kept and counted
    out = _decompose(capsys, a)  # back to full resolution: nothing to recompute
    assert "0 computed, 3 reused" in out, out
    # two scenes in one cache folder keep each other's entries
    b = _copy(demo, tmp_path / "b", gain=2.0)
    cache = tmp_path / "shared"
    _decompose(capsys, a, "--cache", cache)
    out = _decompose(capsys, b, "--cache", cache)
    assert "3 computed" in out and "also holds 3 entries" in out, out
    out = _decompose(capsys, a, "--cache", cache)
    assert "0 computed, 3 reused" in out, out
    # --prune is the explicit way: it deletes what this scene does not use at these settings
    out = _decompose(capsys, a, "--cache", cache, "--prune")
    assert "--prune: deleted 3 entries" in out, out
    assert "3 computed" in _decompose(capsys, b, "--cache", cache)


def test_train_keeps_and_notes_other_resolutions_entries(demo, tmp_path, capsys):
    from retinexgs.retinex.cache import iter_decompositions

    a = _copy(demo, tmp_path / "a")
    _decompose(capsys, a, "--set", "data.downscale=2")
    root = a / "retinex_cache"
    n = len(list(root.rglob("*.npz")))
    # what train runs: the full-resolution views, sweep=True (announce: one line on stderr)
    paths = [v.image_path for v in load_scene(a).train]
    capsys.readouterr()
    list(iter_decompositions(paths, "lime", None, root, progress=False, sweep=True))
    err = capsys.readouterr().err
    assert len(list(root.rglob("*.npz"))) == n + 3
    assert "also holds 3 entries" in err and "--prune" in err and len(err.strip().splitlines()) == 1, err


# ---- item 9: decompose's full-disk message names its own option --------------------------------------------------

def test_decompose_on_a_full_disk_names_the_cache_option(demo, tmp_path, capsys, monkeypatch):
    a = _copy(demo, tmp_path / "a")

    def full(self, fp, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Image.Image, "save", full)  # the downscaled copies are the first files written
    code, out, err = run_cli(["decompose", "--data", a, "--method", "lime", "--quiet", "--cache", tmp_path / "c",
                              "--set", "data.downscale=2"], capsys)
    assert code == 2, err
    assert "no space left on device writing" in err and "write elsewhere with --cache DIR" in err, err
    assert "--out" not in err and "Traceback" not in err, err


def test_decomposer_params_from_several_sources_add_up_and_a_new_method_resets_them():
    """Two `--set decomposer.params.X` keep both (they replaced each other); switching the method drops the old
    method's params; `params={}` resets them."""
    from retinexgs.run.config import load_config

    cfg = load_config([], ["decomposer.params.beta=0.3", "decomposer.params.cg_max_iter=50"])
    assert cfg.decomposer.params["beta"] == 0.3 and cfg.decomposer.params["cg_max_iter"] == 50
    cfg = load_config([], ["decomposer.params.beta=0.3", "decomposer.method=lime"])
    assert cfg.decomposer.method == "lime" and cfg.decomposer.params == {}
    cfg = load_config([], ["decomposer.params.beta=0.3", "decomposer.params={}"])
    assert cfg.decomposer.params == {}
