"""The ``retinexgs bench`` sub-command: ``retinexgs bench NAME [options]`` runs the benchmark NAME exactly as
``python -m retinexgs.bench NAME [options]`` does (the same dispatcher, :mod:`retinexgs.bench.__main__`)."""
from __future__ import annotations

import argparse


class _BenchHelp(argparse.Action):
    """``retinexgs bench --help``: the dispatcher's list of benchmarks (argparse's own help would show only
    NAME), then exit 0. ``retinexgs bench NAME --help`` is NAME's own help: its options reach NAME."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        from retinexgs.bench.__main__ import help_text  # lazy: reads the benchmarks' docstrings

        print(help_text("retinexgs bench"))
        parser.exit(0)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench`` sub-command to the CLI's sub-parsers."""
    p = sub.add_parser("bench", add_help=False,
                       help="run a benchmark (raster, lr3m, fps, quality, scale, denoise, proxy, retone, train-speed, "
                            "darken); "
                            "bench --help lists them",
                       description="Run one RetinexGS benchmark, as python -m retinexgs.bench NAME does (figures "
                                   "and how to read them: docs/benchmarks.md). retinexgs bench --help lists the "
                                   "benchmarks; retinexgs bench NAME --help gives NAME's options.")
    # Own -h/--help (add_help=False): argparse's would list only NAME; the options after NAME are NAME's own,
    # passed on untouched (argparse.REMAINDER), so NAME --help reaches the benchmark.
    p.add_argument("-h", "--help", nargs=0, action=_BenchHelp, help="list the benchmarks and what each measures")
    p.add_argument("bench_argv", nargs=argparse.REMAINDER, metavar="NAME [options]",
                   help="the benchmark and its options (retinexgs bench NAME --help)")
    p.set_defaults(func=_bench)


def _bench(args: argparse.Namespace) -> int:
    from retinexgs.bench.__main__ import main  # lazy: a benchmark loads torch and more

    return main(list(args.bench_argv), prog="retinexgs bench")
