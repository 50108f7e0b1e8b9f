"""Issue 52 stage 3b's input: a camera raw view keeps its unclipped float values (negative noise around black,
light past white) through the undistort/downscale cache, which averages in linear light and stores a float
``.npy``; every other photo still gets its 8-bit PNG copy, as before.

Fixtures: tiny DNGs written by the simulator (retinexgs.data.raw_sim) in tmp_path; never the shared data.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from retinexgs.data import camera_raw, images
from retinexgs.data.camera import Intrinsics
from retinexgs.data.raw_sim import RawCamera, capture_mosaic, write_raw_view
from retinexgs.data.sensor import SensorModel
from retinexgs.data.srgb import linear_to_srgb_extended, srgb_to_linear_extended
from retinexgs.data.undistort import (cache_path_for, output_camera, plan_paths, process_all, process_image,
                                      resize_linear, undistort_rgb, undistorted_camera)
from retinexgs.errors import UserError

cv2 = pytest.importorskip("cv2", reason="opencv is needed for undistortion")

W, H = 48, 36  # even: downscale 2 -> 24x18, whole 2x2 blocks
PINHOLE = Intrinsics(W, H, 40.0, 40.0, W / 2, H / 2)
DISTORTED = Intrinsics(W, H, 40.0, 40.0, W / 2, H / 2, (-0.2, 0.05, 0.0, 0.0))


def _dark_scene(w: int = W, h: int = H) -> np.ndarray:
    """A near-black sRGB ramp with one bright patch: noise around black goes negative, the patch stays high."""
    x = np.linspace(0.0, 0.08, w)[None, :, None]
    img = np.broadcast_to(x, (h, w, 3)).copy()
    img[h // 3: h // 2, w // 3: w // 2] = 0.9
    return img


@pytest.fixture(scope="module")
def raw_folder(tmp_path_factory) -> Path:
    """A scene folder with low/v0.dng (noisy, dark: negative values unclipped) and low/v1.png."""
    root = tmp_path_factory.mktemp("rawcache") / "scene"
    (root / "low").mkdir(parents=True)
    cam, model = RawCamera(), SensorModel(full_well=1500.0, read_noise=6.0)
    rng = np.random.default_rng(7)
    write_raw_view(root / "low" / "v0.dng", capture_mosaic(_dark_scene(), model, cam, 1.0, rng), cam, model, 1.0)
    png = np.random.default_rng(1).integers(0, 256, (H, W, 3), dtype=np.uint8)
    Image.fromarray(png).save(root / "low" / "v1.png")
    return root


def _block_mean_reference(encoded: np.ndarray) -> np.ndarray:
    """The linear-light 2x2 mean of extended-encoded values, computed independently in float64."""
    light = srgb_to_linear_extended(encoded.astype(np.float64))
    h, w = light.shape[:2]
    mean = (light[0::2, 0::2] + light[1::2, 0::2] + light[0::2, 1::2] + light[1::2, 1::2]) / 4.0
    assert mean.shape == (h // 2, w // 2, 3)
    return linear_to_srgb_extended(mean)


def _cache(root: Path, tmp_path: Path, src: Path, cam: Intrinsics, downscale: float) -> Path:
    jobs: list = []
    (tmp_path / "cache").mkdir(exist_ok=True)  # as build_scene does before process_all
    mapping = plan_paths([src], root, tmp_path / "cache", cam, downscale, jobs)
    process_all(jobs, tmp_path / "cache")
    return mapping[src]


def test_a_raw_view_keeps_negative_values_through_a_downscale_by_2(raw_folder, tmp_path):
    src = raw_folder / "low" / "v0.dng"
    source = camera_raw.read_view_srgb(src, clip=False)
    assert source.min() < -0.01 and source.max() > 0.5  # the fixture has noise below black (the test can fail)
    dst = _cache(raw_folder, tmp_path, src, PINHOLE, 2)
    assert dst.suffix == ".npy" and dst.is_file() and dst.parent.name == "low"
    assert dst == cache_path_for(src, raw_folder, tmp_path / "cache", PINHOLE, 2)

    got = images.read_image_float(dst, unclipped=True)
    assert got.dtype == np.float32 and got.shape == (H // 2, W // 2, 3)
    assert images.image_size(dst) == (W // 2, H // 2)
    want = _block_mean_reference(source)
    assert (got < 0).sum() > 10 and np.array_equal(got < 0, want < 0)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    # averaging the ENCODED values instead would differ (why the cache works in linear light)
    encoded_mean = (source[0::2, 0::2] + source[1::2, 0::2] + source[0::2, 1::2] + source[1::2, 1::2]) / 4
    assert np.abs(encoded_mean - want).max() > 1e-3

    # read as a photo (the default), the same copy is clipped to [0, 1]; so is the tensor, and the 8-bit read
    clipped = images.read_image_float(dst)
    assert clipped.min() == 0.0 and clipped.max() <= 1.0
    np.testing.assert_array_equal(clipped, np.clip(got, 0.0, 1.0))
    np.testing.assert_array_equal(images.load_image_tensor(dst).numpy(), clipped)
    np.testing.assert_array_equal(images.load_image_tensor(dst, unclipped=True).numpy(), got)
    assert images.read_image(dst).dtype == np.uint8


def test_a_clipped_raw_read_equals_the_clipped_unclipped_read(raw_folder):
    """read_image_float(raw) is today's clipped view; unclipped=True only removes the clip."""
    src = raw_folder / "low" / "v0.dng"
    clipped, free = images.read_image_float(src), images.read_image_float(src, unclipped=True)
    np.testing.assert_array_equal(clipped, camera_raw.read_view_srgb(src))
    assert free.min() < 0 and clipped.min() >= 0
    np.testing.assert_allclose(clipped, np.clip(free, 0, 1), atol=2e-6)


def test_a_distorted_raw_view_is_remapped_in_linear_light(raw_folder, tmp_path):
    src = raw_folder / "low" / "v0.dng"
    dst = _cache(raw_folder, tmp_path, src, DISTORTED, 2)
    assert dst.suffix == ".npy" and "undistorted" in dst.parts
    light = srgb_to_linear_extended(camera_raw.read_view_srgb(src, clip=False))
    remapped = undistort_rgb(light, DISTORTED, undistorted_camera(DISTORTED))
    out = output_camera(DISTORTED, 2)
    want = linear_to_srgb_extended(resize_linear(remapped, out.width, out.height))
    got = images.read_image_float(dst, unclipped=True)
    assert got.shape == (out.height, out.width, 3) and got.min() < 0
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)


def test_resize_linear_is_the_exact_block_mean_and_area_for_other_factors():
    rng = np.random.default_rng(0)
    a = rng.normal(0.0, 1.0, (6, 9, 3)).astype(np.float32)
    got = resize_linear(a, 3, 2)  # 3x3 blocks
    want = a.astype(np.float64).reshape(2, 3, 3, 3, 3).mean(axis=(1, 3)).astype(np.float32)
    np.testing.assert_array_equal(got, want)
    odd = resize_linear(a, 4, 5)  # non-integer factors: OpenCV's area average keeps the mean and the sign
    assert odd.shape == (5, 4, 3) and odd.dtype == np.float32
    assert abs(float(odd.mean()) - float(a.mean())) < 0.05 and odd.min() < 0
    assert resize_linear(a, 9, 6) is a


def test_a_png_source_still_gets_the_same_png_copy(raw_folder, tmp_path):
    src = raw_folder / "low" / "v1.png"
    dst = _cache(raw_folder, tmp_path, src, PINHOLE, 2)
    assert dst.suffix == ".png"
    # what the cache wrote before raw views had their own format: 8-bit read, Pillow box filter, PNG level 1
    rgb = images.resize_image(images.read_image(src), W // 2, H // 2)
    buf = io.BytesIO()
    Image.fromarray(rgb, "RGB").save(buf, format="PNG", compress_level=1)
    assert dst.read_bytes() == buf.getvalue()
    # non-raw photos ignore unclipped
    np.testing.assert_array_equal(images.read_image_float(src, unclipped=True), images.read_image_float(src))


def test_npy_is_a_cache_format_not_a_photo_type(raw_folder, tmp_path):
    assert ".npy" not in images.IMAGE_EXTENSIONS
    folder = tmp_path / "photos"
    folder.mkdir()
    np.save(folder / "a.npy", np.zeros((4, 4, 3), np.float32))
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(folder / "b.png")
    assert [p.name for p in images.list_images(folder)] == ["b.png"]
    assert not images.is_image_file(folder / "a.npy")


def _truncated(path: Path) -> None:
    np.save(path, np.ones((8, 8, 3), np.float32))
    path.write_bytes(path.read_bytes()[:-50])


@pytest.mark.parametrize("make, words", [
    (_truncated, ()),
    (lambda p: p.write_bytes(b"not a numpy file at all"), ()),
    (lambda p: np.save(p, np.ones((8, 8, 3), np.float64)), ("float64",)),
    (lambda p: np.save(p, np.ones((8, 8), np.float32)), ("8x8",)),
    (lambda p: np.save(p, np.ones((8, 8, 4), np.float32)), ("8x8x4",)),
    (lambda p: np.save(p, np.full((8, 8, 3), np.nan, np.float32)), ("non-finite",)),
    (lambda p: np.save(p, np.array([{"a": 1}], dtype=object), allow_pickle=True), ()),
], ids=["truncated", "garbage", "float64", "2d", "4-channels", "nan", "pickle"])
def test_a_corrupt_npy_gives_one_line_naming_the_file(tmp_path, make, words):
    path = tmp_path / "low" / "v0-0123456789abcdef.npy"
    path.parent.mkdir()
    make(path)
    for read in (images.read_image_float, lambda p: images.read_image_float(p, unclipped=True)):
        with pytest.raises(UserError) as info:
            read(path)
        msg = str(info.value)
        assert str(path) in msg and "\n" not in msg and "cannot read cached image" in msg, msg
        for w in words:
            assert w in msg, msg
    if "non-finite" not in words:  # the size read (header only) refuses the same file
        with pytest.raises(UserError, match="cannot read cached image"):
            images.image_size(path)


def test_a_missing_npy_names_the_file(tmp_path):
    with pytest.raises(UserError, match=r"image .*gone\.npy does not exist"):
        images.read_image_float(tmp_path / "gone.npy")


def test_an_existing_copy_is_reused_not_rewritten(raw_folder, tmp_path):
    src = raw_folder / "low" / "v0.dng"
    dst = _cache(raw_folder, tmp_path, src, PINHOLE, 2)
    marker = np.full((H // 2, W // 2, 3), 0.25, np.float32)
    np.save(dst, marker)  # the name is the content key: an existing file is trusted as this content's copy
    process_image(src, dst, PINHOLE, output_camera(PINHOLE, 2))
    np.testing.assert_array_equal(images.read_image_float(dst), marker)
