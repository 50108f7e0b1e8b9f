"""``python -m retinexgs.bench NAME [options]`` (or ``retinexgs bench NAME [options]``): run one benchmark script
(raster, lr3m, fps, quality, scale, ...)."""
import ast
import importlib.util
import sys
import textwrap
from pathlib import Path
from typing import List, Optional

from retinexgs.openmp import bound_openmp_spinning

BENCHES = {"raster": "retinexgs.bench.raster", "lr3m": "retinexgs.bench.lr3m", "fps": "retinexgs.bench.fps",
           "quality": "retinexgs.bench.quality", "scale": "retinexgs.bench.scale",
           "denoise": "retinexgs.bench.denoise", "bigraw": "retinexgs.bench.bigraw",
           "proxy": "retinexgs.train.benchmarks.proxy", "retone": "retinexgs.train.benchmarks.retone",
           "train-speed": "retinexgs.train.benchmarks.speed", "darken": "retinexgs.bench.darken"}


def _load(name: str):
    """The benchmark's module, imported by name in the source (not from a string), so that the import contracts
    see every edge: the three training benchmarks are this dispatcher's one declared exception to "bench imports
    nothing from train" (.importlinter). Imported here, not at the top: torch is slow to load for --help."""
    if name == "raster":
        from retinexgs.bench import raster as module
    elif name == "lr3m":
        from retinexgs.bench import lr3m as module
    elif name == "fps":
        from retinexgs.bench import fps as module
    elif name == "quality":
        from retinexgs.bench import quality as module
    elif name == "scale":
        from retinexgs.bench import scale as module
    elif name == "bigraw":
        from retinexgs.bench import bigraw as module
    elif name == "darken":
        from retinexgs.bench import darken as module
    elif name == "denoise":
        from retinexgs.bench import denoise as module
    elif name == "proxy":
        from retinexgs.train.benchmarks import proxy as module
    elif name == "retone":
        from retinexgs.train.benchmarks import retone as module
    else:
        from retinexgs.train.benchmarks import speed as module
    return module


PROG = "python -m retinexgs.bench"


def usage(prog: str = PROG) -> str:
    """The usage line of ``prog`` (``python -m retinexgs.bench`` or ``retinexgs bench``)."""
    return f"usage: {prog} {{{','.join(BENCHES)}}} [options]"


USAGE = usage()


def _summary(module: str) -> str:
    """The first paragraph of a benchmark's docstring, read without importing it (torch is slow to load)."""
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.origin:
        return "(not part of this build)"
    doc = ast.get_docstring(ast.parse(Path(spec.origin).read_text(encoding="utf-8"))) or ""
    return " ".join(doc.split("\n\n")[0].split()).replace("``", "")


def help_text(prog: str = PROG) -> str:
    """``--help``: the usage line and one entry per benchmark."""
    intro = ("Run one RetinexGS benchmark (figures and how to read them: docs/benchmarks.md). Each benchmark "
             f"has its own options: {prog} NAME --help")
    lines = [usage(prog), "", *textwrap.wrap(intro, 110), "", "benchmarks:"]
    for name, module in BENCHES.items():
        lines += textwrap.wrap(_summary(module), 110, initial_indent=f"  {name:<13}", subsequent_indent=" " * 15)
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None, prog: str = PROG) -> int:
    """Run the benchmark ``argv[0]`` with the options ``argv[1:]`` (default: the command line's); the exit code.
    ``prog``: how the messages name the command (``retinexgs bench`` dispatches here)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in ("-h", "--help", "help"):
        print(help_text(prog))
        return 0
    if not argv or argv[0] not in BENCHES:
        unknown = f"unknown benchmark {argv[0]!r}; " if argv else ""
        print(f"{usage(prog)}\n{prog}: error: {unknown}choose one of {', '.join(BENCHES)} "
              "(--help lists what each measures)", file=sys.stderr)
        return 2
    name = argv[0]
    if name in ("quality", "proxy", "retone", "scale", "bigraw"):  # trainings in child processes (scale: the scene's writer)
        bound_openmp_spinning()  # before torch loads; these often share the CPU with trainings (docs/benchmarks.md)
    try:
        module = _load(name)
    except ModuleNotFoundError as exc:
        if exc.name != BENCHES[name]:  # a missing dependency (torch, gsplat...) is not a missing benchmark
            raise
        print(f"benchmark {name!r} is not part of this build", file=sys.stderr)
        return 2
    return int(module.main(argv[1:]) or 0)


def _run_from_shell() -> int:
    """``python -m retinexgs.bench``: a user error is one line and exit code 2, as from ``retinexgs bench``."""
    from retinexgs.errors import UserError
    try:
        return main()
    except UserError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(_run_from_shell())
