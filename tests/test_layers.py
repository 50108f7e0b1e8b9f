"""The package's import layering (issue 33): the import-linter contracts in .importlinter hold, and they are able
to fail (a circle or an upward import written into a copy of the package is caught)."""
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def lint(root: Path) -> subprocess.CompletedProcess:
    code = ("import sys; from importlinter.cli import lint_imports; "
            "sys.exit(lint_imports(config_filename='.importlinter', no_cache=True))")
    return subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True,
                          env={"PYTHONPATH": str(root), "PATH": ""})


def test_the_layer_contracts_hold():
    res = lint(ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "3 kept, 0 broken" in res.stdout, res.stdout


def copy_package(tmp_path: Path) -> Path:
    shutil.copytree(ROOT / "retinexgs", tmp_path / "retinexgs", ignore=shutil.ignore_patterns("*.so", "__pycache__"))
    shutil.copy(ROOT / ".importlinter", tmp_path / ".importlinter")
    return tmp_path


def test_an_upward_import_breaks_the_layers(tmp_path):
    root = copy_package(tmp_path)
    f = root / "retinexgs" / "export" / "ply.py"
    f.write_text("import retinexgs.train.trainer  # an export module reading train/\n" + f.read_text())
    res = lint(root)
    assert res.returncode != 0
    assert "retinexgs.export is not allowed to import retinexgs.train" in res.stdout, res.stdout


def test_a_circle_between_modules_is_caught(tmp_path):
    root = copy_package(tmp_path)
    f = root / "retinexgs" / "bench" / "raster_ours.py"
    f.write_text(f.read_text() + "\nimport retinexgs.bench.raster  # noqa: E402  (a circle: raster imports this)\n")
    res = lint(root)
    assert res.returncode != 0
    assert "No cycles are allowed in retinexgs.bench" in res.stdout, res.stdout
