"""Lazy access to the compiled kernel library ``retinexgs._C``."""
from __future__ import annotations

import functools
from pathlib import Path
from types import ModuleType


@functools.lru_cache(maxsize=None)
def kernels() -> ModuleType:
    """Import ``retinexgs._C`` on first use, with an actionable message if it was not built."""
    import torch  # noqa: F401  (loads libtorch before the extension)

    try:
        from retinexgs import _C  # lazy: a missing build fails here, with the message below
    except ImportError as exc:
        import retinexgs  # only to name the folder in the message

        where = Path(retinexgs.__file__).resolve().parent
        raise ImportError(
            f"retinexgs._C (the compiled rasterizer) could not be loaded from {where}: {exc}. "
            "From the source folder (the one holding setup.py), install with "
            "`pip install --no-build-isolation -e \".[test]\"`, which builds it in place against the "
            "installed torch (or build it alone: `python setup.py build_ext --inplace`)."
        ) from exc
    return _C


def set_num_threads(n: int) -> None:
    """Set the OpenMP thread count of the CPU kernels (0, the default: follow ``torch.get_num_threads()``)."""
    if not isinstance(n, int) or n < 0:
        raise ValueError(f"num_threads must be a non-negative integer, got {n!r}")
    kernels().set_num_threads(n)


def get_num_threads() -> int:
    """The OpenMP thread count the CPU kernels use."""
    return int(kernels().get_num_threads())


def has_cuda() -> bool:
    """Whether the kernel library was built with its CUDA kernels."""
    return bool(kernels().has_cuda)
