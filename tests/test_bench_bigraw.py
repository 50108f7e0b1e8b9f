"""The 12 MP raw night scene benchmark (``python -m retinexgs.bench bigraw``, issue 65), at a tiny size on the CPU:
end to end (generate, darken --raw, a training of the DNGs with its priors inside), the second call reading the
finished row back, the limit's clean cut-off, the row syntax, and bad options as one line."""
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from retinexgs.bench import bigraw

TINY = ["--views", "4", "--test-views", "1", "--width", "48", "--height", "36", "--supersample", "1",
        "--points", "500", "--device", "cpu", "--jobs", "2", "--steps", "5"]


def test_end_to_end_writes_its_table_and_reuses_finished_rows(tmp_path, capsys):
    out = tmp_path / "out"
    argv = TINY + ["--scenes-dir", str(tmp_path / "scenes"), "--out", str(out), "--configs", "default"]
    assert bigraw.main(argv) == 0, capsys.readouterr().err
    report = json.loads((out / "bigraw.json").read_text())
    (row,) = report["rows"]
    assert row["status"] == "ok" and row["steps"] == 5, row
    assert report["darken"]["seconds"] > 0 and not report["darken"]["reused"]
    assert (out / "dark" / "raw" / "low" / "0000.dng").is_file()
    # the priors were made inside the training (its own cache folder, removed after it), not beforehand
    assert not (out / "dark" / "raw" / "retinex_cache").exists() and not (out / "caches" / "1-default").exists()
    assert "data.cache_dir=" in row["command"] and "steps=5" in row["command"]
    assert row["time_to_first_step"] > 0 and row["steps_per_second"] > 0 and row["host_rss_gb"] > 0
    assert 0 < row["views_set_up_seconds"] < row["time_to_first_step"]  # metrics.json's train.views_set_up_seconds
    # a finished row is tied to the darkening it trained on (a new darkening retrains it)
    assert row["dark_made"] == json.loads((out / "dark.json").read_text())["made"] is not None
    assert row["psnr"] is not None and row["psnr_gt_mean"] is not None
    assert row["total_seconds"] == pytest.approx(report["darken"]["seconds"] + row["wall_seconds"], abs=0.2)
    md = (out / "bigraw.md").read_text()
    assert "| `default` | ok | 5 |" in md and "darken --raw:" in md
    capsys.readouterr()
    # the same command again: the darkening and the finished row are read back, nothing trained
    stamp = (out / "runs" / "1-default" / "metrics.json").stat().st_mtime_ns
    assert bigraw.main(argv) == 0
    log = capsys.readouterr().out
    assert "darken: reusing" in log and "reused the finished run" in log
    assert (out / "runs" / "1-default" / "metrics.json").stat().st_mtime_ns == stamp
    again = json.loads((out / "bigraw.json").read_text())
    assert again["rows"][0]["status"] == "ok" and again["darken"]["reused"]


def test_rows_and_their_commands(tmp_path):
    rows = bigraw.parse_configs("default|train.resolution=[[0.8,4],[0.95,2]]| ablations/x  steps=3000 ")
    assert [r["config"] for r in rows] == ["default", "default", "ablations/x"]
    assert rows[1]["sets"] == ["train.resolution=[[0.8,4],[0.95,2]]"] and rows[2]["label"] == "ablations/x steps=3000"
    cmd = bigraw.train_command(tmp_path / "d", tmp_path / "r", tmp_path / "c", "cpu", rows[2], 10000, ["seed=1"])
    assert "steps=10000" not in cmd and cmd[-2:] == ["--set", "steps=3000"]  # the row's own steps win
    assert cmd[cmd.index("--config") + 1] == "ablations/x" and f"data.cache_dir={tmp_path / 'c'}" in cmd
    cmd = bigraw.train_command(tmp_path / "d", tmp_path / "r", tmp_path / "c", "cpu", rows[1], 10000, [])
    assert "steps=10000" in cmd and "--config" not in cmd
    assert bigraw.run_name(2, rows[1]["label"]) == "2-train.resolution-0.8-4-0.95-2"


def test_a_training_past_the_limit_is_stopped_and_its_progress_read(tmp_path):
    script = ("import json, signal, sys, time\n"
              "def stop(*a):\n    print('checkpoint', flush=True); sys.exit(130)\n"
              "signal.signal(signal.SIGINT, stop)\n"
              f"open({str(tmp_path / 'train_log.jsonl')!r}, 'w').write("
              "json.dumps({'step': 40, 'seconds': 2.0}) + '\\n' + json.dumps({'step': 41, 'event': 'x'}) + '\\n')\n"
              "time.sleep(60)\n")
    t0 = time.monotonic()
    rc, wall, rss, cut = bigraw.run_until([sys.executable, "-c", script], tmp_path / "log", time.monotonic() + 1.5)
    assert cut and rc == 130 and wall < 20 and time.monotonic() - t0 < 20
    assert "checkpoint" in (tmp_path / "log").read_text()
    lines = (tmp_path / "log").read_text().splitlines()
    assert any(re.fullmatch(r"\[ +\d+\.\d s\] checkpoint", line) for line in lines), lines
    assert bigraw._progress(tmp_path) == (40, 2.0)
    rc, _, _, cut = bigraw.run_until([sys.executable, "-c", "pass"], tmp_path / "log2", None)
    assert rc == 0 and not cut


@pytest.mark.parametrize("option, message", [
    (["--configs", "default ablations/x"], "two config names"),
    (["--configs", "default||steps=3"], "an empty row"),
    (["--configs", "=3"], "has no key"),
    (["--configs", "default|default"], "listed twice"),
    (["--steps", "0"], "--steps 0"),
    (["--set", "steps"], "KEY=VALUE"),
    (["--limit", "-1"], "--limit"),
    (["--test-views", "0"], "--test-views >= 1"),
])
def test_a_bad_option_is_one_line(tmp_path, capsys, option, message):
    assert bigraw.main(["--device", "cpu", "--out", str(tmp_path / "o")] + option) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("python -m retinexgs.bench bigraw: error:") and message in err[0], err
    assert not (tmp_path / "o").exists()


def _photo_scene(folder: Path) -> Path:
    for sub in ("high", "low"):
        (folder / sub).mkdir(parents=True)
        for i in range(2):
            Image.fromarray(np.full((12, 16, 3), 40 * (i + 1), np.uint8)).save(folder / sub / f"{i}.png")
    return folder


def test_a_scene_without_high_or_a_foreign_dark_folder_is_refused(tmp_path, capsys):
    scene = _photo_scene(tmp_path / "s")
    out = tmp_path / "out"
    (out / "dark").mkdir(parents=True)
    (out / "dark" / "mine.txt").write_text("keep")
    assert bigraw.main(["--scene", str(scene), "--device", "cpu", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "did not make it" in err[0], err
    assert (out / "dark" / "mine.txt").read_text() == "keep"
    (tmp_path / "bare").mkdir()
    assert bigraw.main(["--scene", str(tmp_path / "bare"), "--device", "cpu", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no high/ folder" in err[0], err


def test_a_progress_bar_keeps_its_last_redraw_and_every_line_its_time(tmp_path):
    script = ("import sys\nsys.stdout.write('start\\n 10%\\r 50%\\r100%\\nend')\n")
    rc, _, _, _ = bigraw.run_until([sys.executable, "-c", script], tmp_path / "log", None)
    lines = (tmp_path / "log").read_text().splitlines()
    assert rc == 0 and [line.split("] ", 1)[1] for line in lines] == ["start", "100%", "end"], lines


def test_a_capped_training_runs_under_the_cap_module(tmp_path):
    rows = bigraw.parse_configs("default")
    cmd = bigraw.train_command(tmp_path / "d", tmp_path / "r", tmp_path / "c", "cuda", rows[0], 100, [], 24.0)
    assert cmd[1:5] == ["-m", "retinexgs.bench.capped", "24", "train"]
    assert bigraw.main(["--gpu-memory-gb", "0"]) == 2


@pytest.mark.parametrize("args, message", [
    (["x", "train"], "GB must be a number"), (["24"], "usage"),
])
def test_the_cap_module_refuses_bad_arguments_in_one_line(args, message):
    r = subprocess.run([sys.executable, "-m", "retinexgs.bench.capped", *args], capture_output=True, text=True)
    assert r.returncode != 0 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_rows_side_by_side_each_train_and_the_table_says_so(tmp_path, capsys):
    out = tmp_path / "out"
    argv = TINY + ["--scenes-dir", str(tmp_path / "scenes"), "--out", str(out), "--configs", "default|steps=3",
                   "--side-by-side"]
    assert bigraw.main(argv) == 0, capsys.readouterr().err
    report = json.loads((out / "bigraw.json").read_text())
    assert report["side_by_side"] is True
    assert [(r["status"], r["steps"]) for r in report["rows"]] == [("ok", 5), ("ok", 3)]
    assert "side by side" in (out / "bigraw.md").read_text()
