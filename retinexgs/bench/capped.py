"""``python -m retinexgs.bench.capped GB ARGS...``: ``python -m retinexgs ARGS...`` with torch's caching allocator
capped at GB gigabytes (2^30) of the GPU, what a smaller card holds (``bench bigraw --gpu-memory-gb 24``: the 12 MP
scene as a 24 GB card runs it, on a larger one). The cap is torch's per-process memory fraction: an allocation past
it fails as it would on that card, and :func:`retinexgs.retinex.lr3m.free_memory_bytes` sees it (LR3M then solves
large photos on tiles, as there). CUDA's own context and kernels are not counted, as on the real card."""
from __future__ import annotations

import runpy
import sys


def main(argv: list) -> None:
    if len(argv) < 2:
        sys.exit("usage: python -m retinexgs.bench.capped GB ARGS... (python -m retinexgs ARGS under a GB cap)")
    try:
        gb = float(argv[0])
    except ValueError:
        sys.exit(f"retinexgs.bench.capped: GB must be a number, got {argv[0]!r}")
    import torch

    if not torch.cuda.is_available():
        sys.exit("retinexgs.bench.capped: no CUDA device to cap")
    total = torch.cuda.get_device_properties(0).total_memory
    if not 0 < gb * 2**30 <= total:
        sys.exit(f"retinexgs.bench.capped: {gb:g} GB is not within this GPU's {total / 2**30:.1f} GB")
    torch.cuda.set_per_process_memory_fraction(gb * 2**30 / total)
    sys.argv = ["retinexgs"] + argv[1:]
    runpy.run_module("retinexgs", run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main(sys.argv[1:])
