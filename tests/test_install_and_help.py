"""Issue 15, first hour of a newcomer: the README's set-up is what CI runs, a source tree without built
kernels stops the tests with one instruction, the dependencies and defaults print no noise, the OpenMP
threads do not spin on a busy machine, and the help says what the commands take."""
import argparse
import ast
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from retinexgs.cli import build_parser, main
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.evaluate.evaluate import save_png
from retinexgs.openmp import SPIN_COUNT
from retinexgs.render import get_num_threads
from retinexgs.retinex.cache import resolve_device
from retinexgs.run.config import load_config
from retinexgs.train.runner import train_run

REPO = Path(__file__).resolve().parent.parent
README = (REPO / "README.md").read_text()
TINY = ["steps=4", "model.max_init_points=200", "decomposer.method=lime"]  # otherwise the default config


def _bash_blocks(markdown: str, heading: str) -> list:
    """The ```bash blocks of one ``## heading`` section, each as a list of non-empty lines."""
    section = markdown.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]
    return [[ln for ln in b.strip().splitlines() if ln.strip()] for b in re.findall(r"```bash\n(.*?)```", section,
                                                                                   re.S)]


def _env(without=(), **extra: str) -> dict:
    """This process' environment less ``without``, plus ``extra``."""
    return {**{k: v for k, v in os.environ.items() if k not in without}, **extra}


# ---- the README's set-up is what CI runs ----------------------------------------------------------------

def test_ci_runs_the_readme_setup_commands_verbatim_before_anything_else():
    blocks = _bash_blocks(README, "Set up")
    assert [len(b) for b in blocks] == [1, 1], "the set-up is two one-line commands"
    install, tests = blocks[0][0], blocks[1][0]
    # Editable: the kernels are built in place, so `import retinexgs` from the repository root (the tests) works.
    assert 'pip install --no-build-isolation -e ".[test]"' in install and "retinexgs demo" in install
    assert tests == "python -m pytest tests -q -p no:cacheprovider"
    ci = [ln.strip() for ln in (REPO / ".ci" / "run").read_text().splitlines()]
    assert install in ci and tests in ci and ci.index(install) < ci.index(tests)
    # Before the README's first command only the environment is prepared: no other install, test or run.
    for line in ci[:ci.index(install)]:
        assert not re.search(r"pytest|torch|retinexgs demo|setup\.py| -e ", line), line


def test_tests_stop_at_once_with_the_install_instruction_when_the_kernels_are_not_built(tmp_path):
    # A copy of the source folder without _C*.so, as the repository root is after a non-editable install.
    shutil.copytree(REPO / "retinexgs", tmp_path / "retinexgs",
                    ignore=shutil.ignore_patterns("_C*.so", "_C*.pyd", "__pycache__"))
    (tmp_path / "tests").mkdir()
    shutil.copy(REPO / "tests" / "conftest.py", tmp_path / "tests")
    (tmp_path / "tests" / "test_one.py").write_text("def test_one():\n    pass\n")
    p = subprocess.run([sys.executable, "-m", "pytest", "tests", "-q", "-p", "no:cacheprovider"], cwd=tmp_path,
                       env=_env(without=["PYTHONPATH"]), capture_output=True, text=True, timeout=120)
    out = p.stdout + p.stderr
    assert p.returncode == pytest.ExitCode.USAGE_ERROR, out
    # Without an install: _C cannot be loaded; beside an editable install of the repository, the copy would
    # borrow the repository's _C. Either way the copy is named with the command that builds its own.
    assert str(tmp_path / "retinexgs") in out
    assert 'pip install --no-build-isolation -e ".[test]"' in out
    assert "passed" not in out and "Traceback" not in out


def test_pycolmap_and_plyfile_are_requirements():
    tree = ast.parse((REPO / "setup.py").read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    requires = ast.literal_eval(next(k.value for k in call.keywords if k.arg == "install_requires"))
    names = {re.split(r"[<>=\[ ]", r, 1)[0] for r in requires}
    assert {"pycolmap", "plyfile"} <= names


# ---- TensorBoard off by default, LPIPS on (shipped weights); one line when asked for and missing ---------------

@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    # 40x32: large enough for LPIPS's AlexNet (31x31 at least)
    return make_demo_scene(tmp_path_factory.mktemp("scene") / "demo", n_train=3, n_test=2, width=40, height=32,
                           n_points=200)


def _train_lines(scene, run, overrides, monkeypatch):
    # As on a machine without tensorboard (LPIPS needs nothing installed: its weights ship with the package).
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)
    logs = []
    train_run(scene, run, [], TINY + overrides, "cpu", progress=False, log=logs.append)
    return logs


def test_default_run_reports_lpips_and_prints_nothing_about_tensorboard(tiny_scene, tmp_path, monkeypatch,
                                                                        one_thread):
    cfg = load_config([])
    assert cfg.log.tensorboard is False and cfg.eval.lpips is True
    logs = _train_lines(tiny_scene, tmp_path / "run", [], monkeypatch)
    assert not [ln for ln in logs if "tensorboard" in ln.lower() or "LPIPS not reported" in ln], logs
    assert len([ln for ln in logs if ln.startswith("test views:") and ", LPIPS 0." in ln]) == 1, logs


def test_asking_for_missing_tensorboard_and_lpips_says_so_once(tiny_scene, tmp_path, monkeypatch, one_thread):
    import retinexgs.evaluate.lpips as lpips_port

    monkeypatch.setattr(lpips_port, "WEIGHTS", tmp_path / "lpips_alex.npz")  # a broken install without the weights
    logs = _train_lines(tiny_scene, tmp_path / "run", ["log.tensorboard=true", "eval.lpips=true"], monkeypatch)
    tb = [ln for ln in logs if "tensorboard" in ln.lower()]
    lp = [ln for ln in logs if ln.startswith("LPIPS not reported")]
    assert len(tb) == 1 and "pip install tensorboard" in tb[0], logs
    assert len(lp) == 1 and "reinstall retinexgs" in lp[0], logs  # two test views, one line with the reason


# ---- OpenMP threads ------------------------------------------------------------------------------------

def _openmp_settings(env: dict) -> str:
    """What libgomp reports at start-up (OMP_DISPLAY_ENV) in a ``retinexgs`` process that loads torch."""
    p = subprocess.run([sys.executable, "-m", "retinexgs", "eval", "--run", "no-such-run", "--device", "cpu"],
                       env=dict(env, OMP_DISPLAY_ENV="VERBOSE", PYTHONPATH=str(REPO)), capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 2 and "no-such-run" in p.stderr  # torch was loaded, then the run refused
    return p.stdout + p.stderr


def test_cli_bounds_openmp_spinning_unless_the_user_chose_a_policy():
    # libgomp's default would show GOMP_SPINCOUNT = '300000' (about 3 ms of spinning per wait).
    mine = ["OMP_WAIT_POLICY", "GOMP_SPINCOUNT"]
    assert f"GOMP_SPINCOUNT = '{SPIN_COUNT}'" in _openmp_settings(_env(without=mine))
    assert "OMP_WAIT_POLICY = 'ACTIVE'" in _openmp_settings(_env(without=mine, OMP_WAIT_POLICY="ACTIVE"))
    assert "GOMP_SPINCOUNT = '0'" in _openmp_settings(_env(without=mine, OMP_WAIT_POLICY="PASSIVE"))
    assert "GOMP_SPINCOUNT = '42'" in _openmp_settings(_env(without=mine, GOMP_SPINCOUNT="42"))


def test_kernels_use_torch_thread_count():
    before = torch.get_num_threads()
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            assert get_num_threads() == n
    finally:
        torch.set_num_threads(before)


# ---- help and the README's commands --------------------------------------------------------------------

def test_every_readme_use_command_parses():
    [lines] = _bash_blocks(README, "Use")
    commands = [shlex.split(ln.split("#", 1)[0]) for ln in lines]
    assert len(commands) >= 8
    for argv in commands:
        assert argv[0] == "retinexgs"
        if argv[1:] not in (["--help"], ["--version"]):  # both print and exit
            build_parser().parse_args(argv[1:])  # argparse exits (a test error) on an unknown option


def test_help_has_descriptions_and_no_markup(capsys):
    parser = build_parser()
    assert "`" not in parser.format_help()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sub in subs.choices.items():
        assert sub.description, f"retinexgs {name} --help has no description"
        assert "`" not in sub.format_help(), name
        assert all(a.help for a in sub._actions), f"retinexgs {name}: an option without help"


def test_bench_help_lists_every_benchmark_and_exits_0():
    """Issue 36: ``python -m retinexgs.bench --help`` printed only a usage line, with exit code 2."""
    from retinexgs.bench.__main__ import BENCHES

    p = subprocess.run([sys.executable, "-m", "retinexgs.bench", "--help"], capture_output=True, text=True,
                       timeout=60, cwd=REPO)
    assert p.returncode == 0 and p.stderr == "", p.stderr
    entries = {ln.split()[0]: ln for ln in p.stdout.split("benchmarks:\n", 1)[1].splitlines() if ln[2:3] != " "}
    assert sorted(entries) == sorted(BENCHES), p.stdout
    assert all(len(ln.split()) > 3 for ln in entries.values()), p.stdout  # each with what it measures
    assert "NAME --help" in p.stdout
    p = subprocess.run([sys.executable, "-m", "retinexgs.bench", "nosuch"], capture_output=True, text=True,
                       timeout=60, cwd=REPO)
    assert p.returncode == 2 and "unknown benchmark 'nosuch'" in p.stderr, p.stderr


def test_decompose_device_auto(tmp_path, monkeypatch, capsys, one_thread):
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto").type == "cuda"
    monkeypatch.undo()
    photos = tmp_path / "photos"
    photos.mkdir()
    save_png(torch.rand(12, 16, 3) * 0.2, photos / "a.png")
    assert main(["decompose", "--data", str(photos), "--device", "auto", "--method", "lime", "--quiet",
                 "--cache", str(tmp_path / "cache")]) == 0
    assert "1 view(s) decomposed" in capsys.readouterr().out
