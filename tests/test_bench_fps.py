"""The FPS benchmark on a tiny trained run (CPU): both stages timed on the same Gaussians, bad runs named."""
import pytest
import torch

from retinexgs.bench.fps import STAGES, benchmark, format_result, main, resize_camera
from retinexgs.render import Camera
from scenes import tiny_trained_run

TINY = ["steps=4", "checkpoint.every=4", "log.tensorboard=false", "model.sh_degree=1", "model.sh_degree_every=2",
        "model.max_init_points=300", "density.start=100", "decomposer.method=lime"]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return tiny_trained_run(tmp_path_factory.mktemp("fps"), TINY, n_test=2, width=40, height=30,
                            n_points=300)[1]


def test_fps_times_full_fused_and_raster_on_resized_cameras(run_dir):
    r = benchmark(run_dir, "cpu", width=50, height=20, frames=3, warmup=1)
    assert (r["width"], r["height"], r["channels"]) == (50, 20, 6)
    assert r["gaussians"] > 0
    for stage in STAGES:
        assert r[stage]["ms"] > 0 and r[stage]["fps"] == pytest.approx(1e3 / r[stage]["ms"])
    assert r["full"]["launches"] is None and r["full (fused)"]["launches"] is None  # counted on CUDA only
    assert r["fused_colors"] is False and "CPU" in r["colors_note"]  # the fused kernel is the GPU's default
    assert r["fused_max_abs_diff"] < 1e-5  # the fused path renders the torch path's image
    text = format_result(r)
    for word in ("full (fused)", "raster", "share", "fused / torch full render", "max |fused - torch|",
                 "torch colours: the CPU default"):
        assert word in text
    assert "launches/frame" not in text


def test_format_shows_launches_when_counted():
    stage = {"ms": 2.0, "fps": 500.0}
    r = {"device": "GPU", "gaussians": 10, "width": 4, "height": 3, "channels": 6, "frames": 2, "fused_colors": True,
         "fused_max_abs_diff": 0.0, "full": dict(stage, ms=4.0, launches=96.0),
         "full (fused)": dict(stage, launches=12.0), "raster": dict(stage, ms=1.0)}
    text = format_result(r)
    assert "96 launches/frame" in text and "12 launches/frame" in text
    assert "0.50x time, 2.0x FPS" in text


def test_resize_camera_scales_each_axis():
    cam = Camera(torch.eye(4), 100.0, 80.0, 32.0, 24.0, 64, 48)
    c = resize_camera(cam, 32, 96)
    assert (c.width, c.height, c.fx, c.cx, c.fy, c.cy) == (32, 96, 50.0, 16.0, 160.0, 48.0)
    same = resize_camera(cam, None, None)
    assert (same.width, same.height, same.fx, same.fy) == (64, 48, 100.0, 80.0)


def test_fps_on_a_folder_that_is_not_a_run(tmp_path, capsys):
    assert main(["--run", str(tmp_path), "--device", "cpu"]) == 2
    assert "not a run folder" in capsys.readouterr().out


@pytest.mark.parametrize("args", [["--frames", "0"], ["--warmup", "-1"], ["--width", "0"], ["--launch-frames", "-2"]])
def test_fps_rejects_bad_arguments(tmp_path, args, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--run", str(tmp_path), "--device", "cpu"] + args)
    assert exc.value.code == 2 and "error" in capsys.readouterr().err
