"""The training-step speed benchmark (CPU): the synthetic step trains, the trainer mode runs, bad sizes are named."""
import argparse

import pytest
import torch

from retinexgs.train.benchmarks.speed import main, measure, parse_size, synthetic_step
from retinexgs.demo.synthetic import make_demo_scene


def test_parse_size():
    assert parse_size("100k") == 100_000 and parse_size("3M") == 3_000_000 and parse_size("2500") == 2500
    for bad in ("0", "-1k", "nan", "abc"):
        with pytest.raises((argparse.ArgumentTypeError, ValueError)):
            parse_size(bad)


def test_synthetic_step_runs_and_measures():
    step = synthetic_step(300, 32, 24, torch.device("cpu"))
    m = measure(step, steps=2, warmup=1, device=torch.device("cpu"))
    assert m["wall_ms"] > 0 and m["free_ms"] > 0
    assert m["gpu_ms"] != m["gpu_ms"]  # NaN: no GPU split on the CPU


def test_cli_synthetic_and_trainer_modes(tmp_path, capsys):
    assert main(["--device", "cpu", "--sizes", "200", "--width", "24", "--height", "16", "--steps", "2",
                 "--warmup", "1"]) == 0
    out = capsys.readouterr().out
    assert "| 200 ours |" in out and "n/a" in out
    scene = make_demo_scene(tmp_path / "scene", n_train=2, n_test=1, width=24, height=18, n_points=150)
    assert main(["--device", "cpu", "--data", str(scene), "--steps", "2", "--warmup", "1",
                 "--config", "demo"]) == 0
    out = capsys.readouterr().out
    assert "| trainer |" in out and "steps 1-" in out


@pytest.mark.parametrize("args", [["--sizes", "0"], ["--steps", "0"], ["--warmup", "-1"], ["--width", "0"]])
def test_cli_rejects_bad_arguments(args, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--device", "cpu"] + args)
    assert exc.value.code == 2 and "error" in capsys.readouterr().err


def test_busy_time_is_the_union_of_spans():
    from retinexgs.train.benchmarks.speed import busy_ms
    assert busy_ms([]) == 0.0
    assert busy_ms([(0, 1000), (500, 1500), (1500, 2000), (3000, 3500)]) == pytest.approx(2.5)  # overlap once
    assert busy_ms([(0, 1000), (0, 1000), (100, 200)]) == pytest.approx(1.0)  # duplicates and nested spans


class _Event:
    def __init__(self, activity_type=None, device_type=None, is_user_annotation=False):
        self.activity_type, self.device_type, self.is_user_annotation = activity_type, device_type, is_user_annotation


def test_gpu_time_counts_kernels_and_copies_not_annotations():
    from retinexgs.train.benchmarks.speed import _is_gpu_work
    cuda = torch.autograd.DeviceType.CUDA
    assert _is_gpu_work(_Event("kernel", cuda)) and _is_gpu_work(_Event("gpu_memcpy", cuda))
    assert _is_gpu_work(_Event("gpu_memset", cuda))
    # torch mirrors record_function ranges onto the GPU timeline; they span the gaps between kernels
    assert not _is_gpu_work(_Event("gpu_user_annotation", cuda, True))
    assert not _is_gpu_work(_Event("cuda_runtime", torch.autograd.DeviceType.CPU))
    # an older torch without activity_type: the device and the annotation flag decide
    assert _is_gpu_work(_Event(None, cuda)) and not _is_gpu_work(_Event(None, cuda, True))
    assert not _is_gpu_work(_Event(None, torch.autograd.DeviceType.CPU))


def test_split_is_flagged_when_gpu_time_exceeds_the_free_running_step(monkeypatch):
    import retinexgs.train.benchmarks.speed as ts
    monkeypatch.setattr(ts, "profile_steps", lambda step, n, dev: {"gpu_ms": 1e6, "launches": 3.0})
    m = ts.measure(lambda: None, 2, 0, torch.device("cpu"))
    assert m["split_ok"] is False and m["overhead_ms"] != m["overhead_ms"]  # NaN, not a negative overhead
    assert "unreliable" in ts._row("x", m)
    monkeypatch.setattr(ts, "profile_steps", lambda step, n, dev: {"gpu_ms": 0.0, "launches": 3.0})
    m = ts.measure(lambda: None, 2, 0, torch.device("cpu"))
    assert m["split_ok"] is True and m["overhead_ms"] == m["wall_ms"] and "unreliable" not in ts._row("x", m)
