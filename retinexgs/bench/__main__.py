"""``python -m retinexgs.bench NAME [options]``: run one benchmark script (raster, lr3m, fps, ...)."""
import importlib
import sys

from retinexgs.openmp import bound_openmp_spinning

BENCHES = {"raster": "retinexgs.bench.raster", "lr3m": "retinexgs.bench.lr3m", "fps": "retinexgs.bench.fps",
           "quality": "retinexgs.bench.quality",
           "proxy": "retinexgs.bench.proxy", "retone": "retinexgs.bench.retone",
           "train-speed": "retinexgs.bench.train_speed"}


def main() -> int:
    if len(sys.argv) < 2 or sys.argv[1] not in BENCHES:
        print(f"usage: python -m retinexgs.bench {{{','.join(BENCHES)}}} [options]", file=sys.stderr)
        return 2
    name = sys.argv[1]
    if name in ("quality", "proxy", "retone"):  # not the timing benchmarks: their figures keep libgomp's default
        bound_openmp_spinning()  # before torch loads; these often share the CPU with trainings (docs/benchmarks.md)
    try:
        module = importlib.import_module(BENCHES[name])
    except ModuleNotFoundError as exc:
        if exc.name != BENCHES[name]:  # a missing dependency (torch, gsplat...) is not a missing benchmark
            raise
        print(f"benchmark {name!r} is not part of this build", file=sys.stderr)
        return 2
    return int(module.main(sys.argv[2:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
