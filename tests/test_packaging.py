"""An installed copy (not the source tree) must carry its configs: ``retinexgs demo`` reads configs/demo.yaml."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_build_py_ships_the_configs_inside_the_package(tmp_path):
    subprocess.run([sys.executable, "setup.py", "-q", "build_py", "--build-lib", str(tmp_path)], cwd=ROOT,
                   check=True, capture_output=True, timeout=120)
    shipped = tmp_path / "retinexgs" / "configs"
    wanted = sorted(p.relative_to(ROOT / "configs") for p in (ROOT / "configs").rglob("*.yaml"))
    assert wanted and sorted(p.relative_to(shipped) for p in shipped.rglob("*.yaml")) == wanted
    # The installed layout is what retinexgs.run.config.configs_dir() looks for next to the package.
    assert (shipped / "default.yaml").read_text() == (ROOT / "configs" / "default.yaml").read_text()
