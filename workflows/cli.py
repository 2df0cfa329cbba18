"""The ``pixloc`` command line."""

import argparse
import logging
import sys
from typing import List, Optional

import pixloc


def _benchmark(args: argparse.Namespace) -> int:
    from .benchmarks import lm
    return lm.main(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pixloc",
        description="PixLoc visual localization at scale: map building, batch localization, training.")
    parser.add_argument("--version", action="version", version=f"pixloc {pixloc.__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    from .cli_build_map import add_arguments as build_map_arguments
    build_map_arguments(sub.add_parser(
        "build-map", help="build a map store (points, observations, reference features)",
        description="Build a map store from a COLMAP model, images, known poses or RGB-D frames."))

    bench = sub.add_parser("benchmark", help="run a benchmark and print figures against its baseline")
    bench_sub = bench.add_subparsers(dest="benchmark", metavar="NAME", required=True)
    lm_parser = bench_sub.add_parser(
        "lm", help="LM iterations per second, batched vs one problem at a time")
    from .benchmarks.lm import add_arguments
    add_arguments(lm_parser)
    lm_parser.set_defaults(func=_benchmark)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not args.verbose:
        for noisy in ("distributed", "bokeh", "tornado"):
            logging.getLogger(noisy).setLevel(logging.WARNING)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
