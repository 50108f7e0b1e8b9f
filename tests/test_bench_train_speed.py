"""The training-step speed benchmark (CPU): the synthetic step trains, the trainer mode runs, bad sizes are named."""
import argparse

import pytest
import torch

from retinexgs.bench.train_speed import main, measure, parse_size, synthetic_step
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
    from retinexgs.bench.train_speed import busy_ms
    assert busy_ms([]) == 0.0
    assert busy_ms([(0, 1000), (500, 1500), (1500, 2000), (3000, 3500)]) == pytest.approx(2.5)  # overlap once
    assert busy_ms([(0, 1000), (0, 1000), (100, 200)]) == pytest.approx(1.0)  # duplicates and nested spans
