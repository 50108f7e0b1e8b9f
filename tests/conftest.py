"""Shared test fixtures, and a guard that the package under test has its compiled kernels."""
from pathlib import Path

from retinexgs.openmp import bound_openmp_spinning

# Before torch loads its OpenMP runtime, as the CLI does: a busy 2-core CI machine does not stall the suite.
bound_openmp_spinning()

import pytest  # noqa: E402
import torch  # noqa: E402


def pytest_sessionstart(session: pytest.Session) -> None:
    """Stop at once, with the install instruction, when the ``retinexgs`` under test (e.g. the source folder
    on sys.path) has no built ``_C`` (otherwise nearly every test fails with the same import error), or
    borrows another copy's ``_C`` through an editable install elsewhere (the kernels would not be the
    ones of the sources under test)."""
    import retinexgs
    from retinexgs.render._backend import kernels

    try:
        C = kernels()
    except ImportError as exc:
        pytest.exit(str(exc), returncode=pytest.ExitCode.USAGE_ERROR)
    here = Path(retinexgs.__file__).resolve().parent
    if Path(C.__file__).resolve().parent != here:
        pytest.exit(f"the tests import retinexgs from {here} but its compiled kernels from {C.__file__}, "
                    f"another copy's build. From {here.parent}, install with "
                    '`pip install --no-build-isolation -e ".[test]"` (or build the kernels in place: '
                    "`python setup.py build_ext --inplace`).", returncode=pytest.ExitCode.USAGE_ERROR)


@pytest.fixture
def one_thread():
    """Tiny tensors: one torch thread avoids oversubscription stalls on a shared 2-core machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def night(tmp_path_factory):
    """``darken --raw`` of a 96x72 demo scene (3 train, 1 test): NIGHT/raw (low/*.dng) and NIGHT/jpeg (the
    denoiser's tests; a test that trains or writes copies it first)."""
    from retinexgs.cli import main
    from retinexgs.demo.synthetic import make_demo_scene

    base = tmp_path_factory.mktemp("denoise_scene")
    src = make_demo_scene(base / "src", n_train=3, n_test=1, width=96, height=72, n_points=200)
    assert main(["darken", "--data", str(src), "--out", str(base / "night"), "--raw", "--quiet"]) == 0
    return base / "night"
