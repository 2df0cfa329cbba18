"""The ``pixloc`` command line."""

import argparse
import logging
import os
import signal
import sys
import threading
from typing import List, Optional

import pixloc


class HelpFormatter(argparse.HelpFormatter):
    """Shows an option's default after its help, unless the help already says it or there is none."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if ("default" in text or default in (None, False, argparse.SUPPRESS, [], ())
                or not action.option_strings):
            return text
        shown = " ".join(map(str, default)) if isinstance(default, (list, tuple)) else default
        return f"{text} (default: {shown})"


class Parser(argparse.ArgumentParser):
    """Every pixloc command's parser: its options show their defaults (``HelpFormatter``)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="pixloc",
        description="PixLoc visual localization at scale: map building, batch localization, training.")
    parser.add_argument("--version", action="version", version=f"pixloc {pixloc.__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--max-image-pixels", type=int, metavar="N",
                        help="refuse images whose header declares more pixels (default 150,000,000; "
                             "also PIXLOC_MAX_IMAGE_PIXELS)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    from .cli_build_map import add_arguments as build_map_arguments
    build_map_arguments(sub.add_parser(
        "build-map", help="build a map store (points, observations, reference features)",
        description="Build a map store from a COLMAP model, images, known poses or RGB-D frames."))

    from .cli_build_map import add_check_store_arguments
    add_check_store_arguments(sub.add_parser(
        "check-store", help="verify every chunk of a map store (checksums, layout)",
        description="Read and decode every chunk of a map store, checking its CRC-32C and the layout; "
                    "bad chunks are listed with their array and images. Exit status 1 if any is bad."))

    from .cli_queries import add_arguments as queries_arguments
    queries_arguments(sub.add_parser(
        "queries", help="query list with intrinsics of uncalibrated photos, from their EXIF",
        description="Write a query list (name MODEL width height params) for photos without calibration: the "
                    "focal length from EXIF (35 mm equivalent, or focal length and focal plane resolution), "
                    "else a default. Exit status 1 if an image was skipped."))

    from .cli_localize import add_arguments as localize_arguments
    from .cli_localize import add_evaluate_arguments
    localize_arguments(sub.add_parser("localize", help="localize queries against a map store",
                                      description="Localize queries (retrieval, prior, PixLoc refinement)."))
    add_evaluate_arguments(sub.add_parser("evaluate", help="pose errors and recall of a localize output"))
    from .cli_localize import add_report_arguments
    add_report_arguments(sub.add_parser("report", help="HTML report of a localize output (plots, examples)"))

    for name in ("build-map", "check-store", "localize", "evaluate", "report"):  # the commands that open a store
        sub.choices[name].add_argument(
            "--storage-options", metavar="JSON", help="fsspec storage options of a store given as a URL, e.g. "
            "'{\"endpoint_url\": \"http://127.0.0.1:9000\"}' (also PIXLOC_STORAGE_OPTIONS; credentials from the "
            "usual environment, AWS_ACCESS_KEY_ID ...; docs/cluster.md)")

    from .demo import add_arguments as demo_arguments
    demo_arguments(sub.add_parser("demo", help="the whole system on a generated synthetic scene (offline)",
                                  description="Generate a scene, build its map, localize queries in four "
                                              "conditions, evaluate, report."))

    from .train import add_arguments as train_arguments
    train_arguments(sub.add_parser(
        "train", help="train the network end to end (resumable)",
        description="End-to-end training from a YAML config (--config: a file, or a packaged config's name), "
                    "resumable; the model card (docs/model_card.md) says how the shipped model was trained."))

    from . import train_whitening
    train_whitening.add_arguments(whitening := sub.add_parser(
        "train-whitening", help="learn the gem-lw descriptor's whitening from posed map images (closed form)",
        description="The learned whitening of the gem-lw global descriptor, from map stores of training scenes "
                    "(their images, relit copies, co-visibility)."))
    whitening.set_defaults(func=train_whitening.main)

    from .evaluate_model import add_arguments as evaluate_model_arguments
    evaluate_model_arguments(sub.add_parser(
        "evaluate-model", help="compare feature models on held-out pairs (same initial poses)",
        description="Pose errors and recall of feature models on the training config's held-out data."))

    bench = sub.add_parser("benchmark", help="run a benchmark and print figures against its baseline")
    bench_sub = bench.add_subparsers(dest="benchmark", metavar="NAME", required=True)
    from .benchmarks import accuracy as bench_accuracy
    from .benchmarks import build_map as bench_build_map
    from .benchmarks import lm as bench_lm
    from .benchmarks import mapping as bench_mapping
    from .benchmarks import localize as bench_localize
    from .benchmarks import query_cpu as bench_query_cpu
    from .benchmarks import query_rate as bench_query_rate
    from .benchmarks import train_step as bench_train_step
    from .benchmarks import rgbd as bench_rgbd
    from .benchmarks import scale as bench_scale
    from .benchmarks import retrieval as bench_retrieval
    from .benchmarks import rigs as bench_rigs
    from .benchmarks import sequences as bench_sequences
    from .benchmarks import search as bench_search
    from .benchmarks import storage as bench_storage
    from .benchmarks import store_latency as bench_store_latency
    from .benchmarks import verification as bench_verification
    for name, module, text in [
            ("lm", bench_lm, "LM iterations per second, batched vs one problem at a time"),
            ("build-map", bench_build_map, "map building: images/s and bytes per observation, 1 vs 2 workers"),
            ("localize", bench_localize, "queries/s with stored features vs the official re-extraction"),
            ("query-cpu", bench_query_cpu, "CPU seconds per query at Cambridge settings per speed-up, with its poses"),
            ("query-rate", bench_query_rate,
             "queries/s at Cambridge settings with batched queries, on a GPU or the CPU, per batch size"),
            ("train-step", bench_train_step, "training steps per CPU hour per change, and what is not the model"),
            ("verification", bench_verification, "precision and rejections of pose verification per threshold"),
            ("rgbd", bench_rgbd,
             "time per 7-Scenes query: gradient maps and points per cell against the official sampler"),
            ("search", bench_search, "recall and time of the search prior against top1, average, hypotheses"),
            ("scale", bench_scale,
             "S1-S5, P3: an Aachen-size store, cities built and localized at size, adding a session"),
            ("storage", bench_storage, "bytes per observation and recall of int8 against float16 feature storage"),
            ("store-latency", bench_store_latency,
             "a query's reads of a store in an S3 bucket at 0-50 ms per request, concurrent vs one at a time"),
            ("accuracy", bench_accuracy,
             "recall, precision and time per prior on every posed real scene, against SIFT + PnP"),
            ("retrieval", bench_retrieval,
             "recall@1/5/10 of each retrieval method per scene and condition, against the co-visibility oracle"),
            ("mapping", bench_mapping,
             "the structure stage: SIFT and matching on 1 vs 2 Dask workers; incremental vs global SfM against "
             "known poses"),
            ("rigs", bench_rigs,
             "a three-camera rig localized as one body against its images one by one, per condition"),
            ("sequences", bench_sequences,
             "a sequence's chunks localized as one body each (simulated odometry with drift) against its frames "
             "one by one")]:
        p = bench_sub.add_parser(name, help=text)
        module.add_arguments(p)
        p.set_defaults(func=module.main)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from .logs import configure
    configure(args.verbose)
    if not args.verbose:
        # read by dask when distributed is first imported (it resets its loggers' levels then)
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
        for noisy in ("distributed", "bokeh", "tornado"):
            logging.getLogger(noisy).setLevel(logging.WARNING)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    from pipeline import runtime
    pixels = getattr(args, "max_image_pixels", None)
    try:  # the run's settings, from the flags else the environment, checked before any work; its tasks carry them
        if pixels is not None and pixels < 1:
            raise runtime.SettingError(f"--max-image-pixels: {pixels} must be a positive number of pixels")
        settings = runtime.RunSettings.from_environment(pixels, getattr(args, "storage_options", None))
    except runtime.SettingError as e:
        print(f"pixloc: error: {e}", file=sys.stderr)
        return 2
    previous = _on_sigterm_stop()
    try:
        with runtime.using(settings):
            return args.func(args)
    except KeyboardInterrupt as e:  # finished shards and images are on disk (executor.dask_client quiets teardown)
        said = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
        print(f"pixloc: {said}; run the same command again to resume", file=sys.stderr)
        return 143 if isinstance(e, Terminated) else 130
    except (ValueError, OSError) as e:  # bad input: SceneError, StoreError, CheckpointError, missing files
        if args.verbose:
            raise
        print(f"pixloc: error: {e}", file=sys.stderr)
        return 2
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


class Terminated(KeyboardInterrupt):
    """SIGTERM (a batch system's or ``timeout``'s stop): the run stops as on Ctrl-C, its cluster closed
    and its finished work kept. Before, glog's failure handler (installed with pycolmap) printed a
    stack dump and the process died without closing anything."""


def _raise_terminated(signum, frame):
    raise Terminated()


def _on_sigterm_stop():
    """SIGTERM raises ``Terminated`` in this (main) thread; returns the handler to restore."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_terminated)


if __name__ == "__main__":
    sys.exit(main())
