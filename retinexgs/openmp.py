"""How long idle OpenMP threads spin before they sleep: set for the process before torch loads libgomp.

libgomp (the OpenMP runtime of torch's Linux wheels, shared by our kernels) lets a thread that reaches a
barrier or waits for the next parallel region spin 300,000 times (about 3 ms) before it sleeps. On a busy
machine those spinning threads hold the cores that the threads they wait for need, and training ran up to
11x slower than on a quiet machine with three other busy processes; sleeping at once (passive waiting)
costs 1.8x on a quiet machine instead, because a step has many short parallel regions. A spin of 3,000
(about 30 us) keeps most of both: docs/benchmarks.md, "Training on a busy CPU".
"""
from __future__ import annotations

import os

SPIN_COUNT = 3000


def bound_openmp_spinning() -> None:
    """Set ``GOMP_SPINCOUNT`` to :data:`SPIN_COUNT` unless the user chose a waiting policy
    (``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT``). Effective only before the OpenMP runtime is loaded."""
    if "OMP_WAIT_POLICY" not in os.environ:
        os.environ.setdefault("GOMP_SPINCOUNT", str(SPIN_COUNT))
