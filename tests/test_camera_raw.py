"""Issue 52, stage 1: camera raw reading (retinexgs.data.camera_raw) and the DNG writer (retinexgs.data.dng).

Every fixture is a DNG written by write_dng in tmp_path; it is read back with rawpy and exifread directly
(the writer is right) and through read_raw (the reader is right). No dev data is used.
"""
from __future__ import annotations

from pathlib import Path

import exifread
import numpy as np
import pytest
import rawpy

from retinexgs.data.camera_raw import (RawPhoto, estimate_noise, exposure_scale, linear_rgb, noise_from_profile,
                                       noise_in_linear_rgb, normalised_mosaic, preview_srgb, read_raw)
from retinexgs.data.dng import write_dng
from retinexgs.errors import UserError

CM = np.array([[0.6461, -0.1164, -0.0857], [-0.3825, 1.1597, 0.2534], [-0.0416, 0.1540, 0.6039]])


def _dng(path: Path, mosaic: np.ndarray, **kw) -> Path:
    args = dict(cfa="RGGB", black_level=512, white_level=16383, as_shot_neutral=(0.5, 1.0, 0.625),
                color_matrix1=CM)
    args.update(kw)
    return write_dng(path, mosaic, **args)


def test_dng_round_trip_every_field(tmp_path):
    rng = np.random.default_rng(1)
    mosaic = rng.integers(0, 4096, (30, 44)).astype(np.uint16)
    blacks = [64, 65, 66, 67]  # per CFA position, row-major: G R / B G
    prof = [2e-3, 1e-5, 1e-3, 2e-5, 3e-3, 3e-5]
    path = write_dng(tmp_path / "a.dng", mosaic, cfa="GRBG", black_level=blacks, white_level=4095,
                     as_shot_neutral=(0.5, 1.0, 0.8), color_matrix1=CM, noise_profile=prof,
                     exposure_time=1 / 30, iso=1600, f_number=2.8)
    # the writer, checked by the libraries
    with rawpy.imread(str(path)) as raw:
        assert np.array_equal(raw.raw_image_visible, mosaic)
        colors = raw.raw_colors_visible[:2, :2]
        black = [[raw.black_level_per_channel[colors[i, j]] for j in range(2)] for i in range(2)]
        assert black == [[64, 65], [66, 67]]
        assert raw.white_level == 4095
        assert [["RGBG"[c] for c in row] for row in colors] == [["G", "R"], ["B", "G"]]
        wb = raw.camera_whitebalance
        assert np.allclose(np.array(wb[:3]) / wb[1], [2.0, 1.0, 1.25], rtol=1e-5)
    with open(path, "rb") as f:
        tags = exifread.process_file(f, details=False)
    assert str(tags["EXIF ExposureTime"]) == "1/30"
    assert float(tags["EXIF FNumber"].values[0]) == pytest.approx(2.8)
    assert tags["EXIF ISOSpeedRatings"].values[0] == 1600
    # the reader
    ph = read_raw(path)
    assert np.array_equal(ph.mosaic, mosaic) and ph.mosaic.dtype == np.uint16
    assert ph.cfa_pattern == "GRBG" and ph.cfa.tolist() == [[1, 0], [2, 1]]
    assert ph.black_level.tolist() == [[64, 65], [66, 67]] and ph.black_map is None
    assert ph.white_level == 4095
    assert np.allclose(ph.white_balance, [2.0, 1.0, 1.25], rtol=1e-6)
    assert np.allclose(ph.xyz_to_cam, CM, atol=1e-6)
    assert np.allclose(ph.cam_to_srgb.sum(axis=1), 1.0)  # white stays white
    assert ph.exposure_time == pytest.approx(1 / 30) and ph.iso == 1600 and ph.f_number == pytest.approx(2.8)
    assert np.allclose(ph.noise_profile, np.reshape(prof, (3, 2)))
    assert ph.notes == []


def test_per_pixel_black_from_deltas():
    """A DNG black with a column delta (BlackLevelDeltaH) becomes a per-pixel map, and linear_rgb uses it."""
    from retinexgs.data.camera_raw import _dng_black_map

    class Tags:  # the tag reader's interface, over a dict of tag -> values
        def get(self, ifd, tag, default=None):
            return ifd.get(tag, default)

    bmap = _dng_black_map(Tags(), {50713: [2, 2], 50714: [100, 101, 102, 103], 50715: list(range(24))}, 24, 24)
    assert bmap[0, :4].tolist() == [100, 102, 102, 104] and bmap[1, :2].tolist() == [102, 104]
    ph = RawPhoto(path=Path("x.dng"), mosaic=(bmap + 50).astype(np.uint16), cfa=np.array([[0, 1], [1, 2]]),
                  cfa_pattern="RGGB", black_level=np.full((2, 2), 101.5, np.float32), white_level=1100.0,
                  white_balance=np.ones(3, np.float32), cam_to_srgb=np.eye(3), black_map=bmap.astype(np.float32))
    assert np.allclose(normalised_mosaic(ph), 50 / (1100 - bmap))


def test_linear_rgb_known_mosaic(tmp_path):
    """Black subtracted per CFA position, divided by (white - black), negative values kept, 2x2 binning exact."""
    h, w = 24, 28
    quad = np.array([[600, 700], [300, 400]], np.uint16)  # R G / G B with black 500: R +100, G +200, G -200, B -100
    mosaic = np.tile(quad, (h // 2, w // 2))
    mosaic[0, 0] = 1500  # one R sample of 1000 above black
    path = _dng(tmp_path / "k.dng", mosaic, black_level=500, white_level=10500, as_shot_neutral=(0.5, 1.0, 0.25))
    ph = read_raw(path)
    x = normalised_mosaic(ph)
    assert x[1, 0] == pytest.approx(-0.02) and x.dtype == np.float32
    rgb = linear_rgb(ph, white_balance=False)
    assert rgb.shape == (h // 2, w // 2, 3) and rgb.dtype == np.float32
    assert rgb[0, 0, 0] == pytest.approx(0.1)
    assert rgb[3, 3, 0] == pytest.approx(0.01)
    assert rgb[3, 3, 1] == pytest.approx(0.0, abs=1e-7)  # mean of +0.02 and -0.02
    assert rgb[3, 3, 2] == pytest.approx(-0.01)  # below black: kept, not clipped
    wb = linear_rgb(ph, white_balance=True)
    assert np.allclose(wb, rgb * np.array([2.0, 1.0, 4.0], np.float32), atol=1e-7)


def _poisson_gaussian(rng, h, w, s, o, black, white):
    """A smooth scene (ramps, a dark band, flat patches) with var = s*x + o in normalised units."""
    yy, xx = np.mgrid[0:h, 0:w]
    x = 0.6 * (xx / w) ** 2 + 0.02 * (yy / h)
    x[: h // 6] = 0.0  # pure read noise
    electrons = rng.poisson(x / s) * s
    y = electrons + rng.normal(0.0, np.sqrt(o), x.shape)
    return np.clip(np.round(black + y * (white - black)), 0, 65535).astype(np.uint16)


def test_noise_profile_exact_and_estimate_within_30_percent(tmp_path):
    s, o = 1e-3, 2e-5
    black, white = 512, 16383
    mosaic = _poisson_gaussian(np.random.default_rng(7), 384, 384, s, o, black, white)
    path = _dng(tmp_path / "n.dng", mosaic, black_level=black, white_level=white, noise_profile=[s, o])
    ph = read_raw(path)
    a, b = noise_from_profile(ph)
    assert np.array_equal(a, [s] * 3) and np.array_equal(b, [o] * 3)
    ea, eb = estimate_noise(ph)
    assert np.all(np.abs(ea / s - 1) < 0.3), ea
    assert np.all(np.abs(eb / o - 1) < 0.3), eb
    # in linear_rgb units: G is the mean of two samples, the white balance scales a by g and b by g^2
    la, lb = noise_in_linear_rgb(a, b, ph)
    assert np.allclose(la, [2 * s, s / 2, 1.6 * s]) and np.allclose(lb, [4 * o, o / 2, 2.56 * o])
    dark = linear_rgb(ph)[: 384 // 12]  # the band at x = 0: variance is b in those units
    assert np.allclose(dark.reshape(-1, 3).var(axis=0), lb, rtol=0.1)


def test_no_profile_gives_none(tmp_path):
    ph = read_raw(_dng(tmp_path / "p.dng", np.full((24, 24), 900, np.uint16)))
    assert noise_from_profile(ph) is None and ph.noise_profile is None


def test_exposure_scale(tmp_path):
    def photo(name, t, iso, fn):
        return RawPhoto(path=Path(name), mosaic=np.zeros((2, 2), np.uint16), cfa=np.array([[0, 1], [1, 2]]),
                        cfa_pattern="RGGB", black_level=np.zeros((2, 2), np.float32), white_level=1.0,
                        white_balance=np.ones(3, np.float32), cam_to_srgb=np.eye(3), exposure_time=t, iso=iso,
                        f_number=fn)

    scales = exposure_scale([photo("a", 1 / 50, 100, 2.0), photo("b", 1 / 25, 100, 2.0),
                             photo("c", 1 / 50, 400, 4.0)])
    assert scales == pytest.approx([1.0, 2.0, 1.0])
    # the aperture missing everywhere cancels; one view lacking ISO is assumed at the median, with a note
    notes = []
    scales = exposure_scale([photo("a", 0.1, 100, None), photo("b", 0.2, 100, None), photo("c", 0.4, None, None),
                             photo("d", 0.4, 100, None)], notes)
    assert scales == pytest.approx([0.5, 1.0, 1.0, 2.0])
    assert len(notes) == 1 and "c:" in notes[0] and "median" in notes[0]
    assert exposure_scale([photo("a", None, None, None)] * 2) == [1.0, 1.0]
    # read from a file's metadata, and the note for a file without it
    ph = read_raw(_dng(tmp_path / "e.dng", np.full((24, 24), 900, np.uint16), exposure_time=0.5, iso=200,
                       f_number=4.0))
    assert ph.exposure() == pytest.approx(0.5 * 200 / 16)
    bare = read_raw(_dng(tmp_path / "f.dng", np.full((24, 24), 900, np.uint16)))
    assert bare.exposure() is None and any("assumed" in n for n in bare.notes)


def test_preview_is_bright_and_8_bit(tmp_path):
    rng = np.random.default_rng(3)
    mosaic = _poisson_gaussian(rng, 64, 64, 1e-3, 1e-5, 512, 16383)  # a dark frame: at most 0.6 of white
    mosaic = ((mosaic.astype(np.int32) - 512) // 20 + 512).astype(np.uint16)  # ~ 3 % of white at most
    ph = read_raw(_dng(tmp_path / "v.dng", mosaic, black_level=512, white_level=16383))
    img = preview_srgb(ph)
    assert img.shape == (32, 32, 3) and img.dtype == np.uint8
    assert 200 <= np.percentile(img.mean(axis=2), 99) <= 255


def _one_line_error(path, match):
    with pytest.raises(UserError) as info:
        read_raw(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg and match in msg, msg
    return msg


@pytest.mark.parametrize("keep", ["half", "8 bytes"])
def test_truncated_dng(tmp_path, keep):
    mosaic = np.random.default_rng(0).integers(0, 4096, (64, 64)).astype(np.uint16)
    path = _dng(tmp_path / "t.dng", mosaic)
    data = path.read_bytes()
    cut = tmp_path / "cut.dng"
    cut.write_bytes(data[: len(data) // 2] if keep == "half" else data[:8])
    _one_line_error(cut, "truncated")


def test_random_bytes_named_nef(tmp_path):
    path = tmp_path / "photo.NEF"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 100_000).astype(np.uint8).tobytes())
    _one_line_error(path, "not a TIFF header")


def test_random_bytes_named_crw_and_raf(tmp_path):
    junk = np.random.default_rng(1).integers(0, 256, 100_000).astype(np.uint8).tobytes()
    (tmp_path / "a.CRW").write_bytes(junk)
    _one_line_error(tmp_path / "a.CRW", "HEAPCCDR")
    (tmp_path / "b.RAF").write_bytes(junk)  # not checked by us: LibRaw's refusal becomes the one line
    _one_line_error(tmp_path / "b.RAF", "LibRaw does not read this format")


def test_missing_file_and_folder(tmp_path):
    _one_line_error(tmp_path / "nope.dng", "no such file")
    (tmp_path / "dir.dng").mkdir()
    _one_line_error(tmp_path / "dir.dng", "not a file")
    (tmp_path / "tiny.dng").write_bytes(b"II*\0")
    _one_line_error(tmp_path / "tiny.dng", "too small")


def test_write_dng_refuses_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="at least 22"):
        write_dng(tmp_path / "s.dng", np.zeros((10, 30), np.uint16))
    with pytest.raises(ValueError, match="cfa"):
        write_dng(tmp_path / "s.dng", np.zeros((30, 30), np.uint16), cfa="RGBB")
    with pytest.raises(ValueError, match="uint16"):
        write_dng(tmp_path / "s.dng", np.zeros((30, 30), np.float32))
    assert not list(tmp_path.iterdir())  # nothing half-written
