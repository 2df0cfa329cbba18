"""``pixloc localize`` and ``pixloc evaluate``."""

import argparse
import json
import time
from collections import Counter
from pathlib import Path

from pipeline.evaluate import DEFAULT_THRESHOLDS, INDOOR_THRESHOLDS, evaluate
from pipeline.features import FeatureConfig
from pipeline.localize import LocalizerConfig
from pipeline.results import read_records
from pipeline.shard import LocalizationJob, RetrievalConfig
from pipeline.store import StoreError, open_store

from .localize import plan_localization, run_dask, run_sync
from .sources import QUERY_KINDS, load_queries


def add_query_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("query_kind", choices=QUERY_KINDS, help="where the queries come from")
    p.add_argument("query_path", type=Path, help="query list file, or dataset root")
    p.add_argument("--query-images", type=Path, help="image folder of a query list or COLMAP model")
    p.add_argument("--query-sequences", type=int, nargs="+", default=[])
    p.add_argument("--query-names", nargs="+", help="keep only these queries")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_query_arguments(p)
    p.add_argument("--store", type=Path, required=True, help="map store built by pixloc build-map")
    p.add_argument("--features", help="feature group of the store (default: its only one)")
    p.add_argument("--output", type=Path, required=True, help="output folder (records, poses, shards)")
    p.add_argument("--pairs", type=Path, help="retrieval pairs file (default: global descriptors)")
    p.add_argument("--retrieval-k", type=int, default=10)
    p.add_argument("--same-tag", help="restrict references to those sharing this tag with the query")
    p.add_argument("--descriptors", type=Path, help="hloc HDF5 global descriptors for retrieval (e.g. NetVLAD)")
    p.add_argument("--prior", choices=["top1", "average", "hypotheses", "poses", "hloc"], default="top1",
                   help="hloc: refinement mode from an hloc _logs.pkl (its PnP poses and inliers)")
    p.add_argument("--prior-poses", type=Path, help="refinement mode: poses file of another pipeline")
    p.add_argument("--hloc-logs", type=Path, help="refinement mode: hloc localization logs (_logs.pkl); "
                   "the store must be built from the SfM model hloc localized against")
    p.add_argument("--point-selection", choices=["all", "inliers", "matched"], default="all",
                   help="with --prior hloc: all points of the references, or hloc's PnP inliers (paper) or matches")
    p.add_argument("--min-points", type=int, default=10, help="fewer 3D points fails a query (official: 10, "
                   "100 in refinement mode)")
    p.add_argument("--levels", type=int, nargs="+", help="optimise only these levels (refinement mode: 0 1)")
    p.add_argument("--scales", type=int, nargs="+", help="run only these of the store's image scales "
                   "(refinement mode: 1)")
    p.add_argument("--num-dbs", type=int, default=5, help="reference images per query")
    p.add_argument("--average-observations", action="store_true")
    p.add_argument("--iters", type=int, default=100, help="LM iterations per level")
    p.add_argument("--shard-size", type=int, default=8)
    p.add_argument("--device", default="cpu")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--sync", action="store_true", help="run in this process, without Dask")
    p.add_argument("--dry-run", action="store_true")
    p.add_argument("--preset", help="dataset preset with the paper's settings (see workflows/presets)")
    p.set_defaults(func=main)
    p.set_defaults(_parser_defaults={a.dest: a.default for a in p._actions})


def store_feature_config(store: Path, key=None) -> FeatureConfig:
    groups = sorted(open_store(store)["features"].group_keys())
    if not groups:
        raise StoreError(f"{store} has no features: run pixloc build-map first.")
    if key is None and len(groups) > 1:
        raise StoreError(f"{store} has several feature groups {groups}: choose one with --features.")
    key = key or groups[0]
    if key not in groups:
        raise StoreError(f"{store} has no feature group {key!r} (it has {groups}).")
    conf = dict(open_store(store)[f"features/{key}"].attrs["config"])
    conf["image_scales"] = tuple(conf["image_scales"])
    return FeatureConfig(**conf)


def main(args: argparse.Namespace) -> int:
    if args.preset:
        from . import presets
        presets.apply(args, presets.load(args.preset), args._parser_defaults)
    fconf = store_feature_config(args.store, args.features)
    if args.scales and not set(args.scales) <= set(fconf.image_scales):
        raise ValueError(f"--scales {args.scales}: the store's features have image scales {list(fconf.image_scales)}.")
    job = LocalizationJob(
        str(args.store), fconf, fconf.model,
        LocalizerConfig(num_dbs=args.num_dbs, average_observations=args.average_observations, num_iters=args.iters,
                        min_points=args.min_points),
        RetrievalConfig("pairs" if args.pairs else "hloc" if args.descriptors else "global",
                        str(args.pairs) if args.pairs else None, args.retrieval_k, args.same_tag,
                        str(args.descriptors) if args.descriptors else None),
        prior=args.prior, device=args.device, prior_poses=str(args.prior_poses) if args.prior_poses else None,
        levels=tuple(args.levels) if args.levels else None, hloc_logs=str(args.hloc_logs) if args.hloc_logs else None,
        point_selection=args.point_selection, scales=tuple(args.scales) if args.scales else None)
    if args.prior == "poses" and not args.prior_poses:
        raise ValueError("--prior poses needs --prior-poses FILE.")
    if args.prior == "hloc" and not args.hloc_logs:
        raise ValueError("--prior hloc needs --hloc-logs FILE (hloc's <results>_logs.pkl).")
    if args.point_selection != "all" and args.prior != "hloc":
        raise ValueError("--point-selection inliers/matched needs --prior hloc (the inliers come from its logs).")
    queries = load_queries(args.query_kind, args.query_path, args.query_images, tuple(args.query_sequences),
                           args.query_names)
    plan = plan_localization(job, queries, args.output, args.shard_size)
    print(plan.describe())
    if args.dry_run:
        return 0
    t0 = time.time()
    if args.sync:
        records = run_sync(plan, progress=True)
    else:
        from distributed import Client, LocalCluster
        client = Client(args.scheduler) if args.scheduler else Client(LocalCluster(
            n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=":0"))
        print(f"Dask dashboard: {client.dashboard_link}")
        with client:
            records = run_dask(plan, client, progress=True)
    counts = Counter("success" if r["success"] else "failed" for r in records)
    print(f"\n{len(records)} queries in {time.time() - t0:.1f} s: {counts['success']} refined, "
          f"{counts['failed']} failed (kept their prior). -> {args.output / 'poses.txt'}")
    for reason, n in Counter(r["reason"] for r in records if not r["success"]).most_common(5):
        print(f"  {n} x {reason}")
    return 0


def add_evaluate_arguments(p: argparse.ArgumentParser) -> None:
    add_query_arguments(p)
    p.add_argument("--output", type=Path, required=True, help="a pixloc localize output folder")
    p.add_argument("--indoor", action="store_true", help="thresholds (5 cm, 5 deg) as for 7-Scenes/Cambridge")
    p.add_argument("--preset", help="take the dataset preset's thresholds")
    p.set_defaults(func=evaluate_main)


def evaluate_main(args: argparse.Namespace) -> int:
    queries = load_queries(args.query_kind, args.query_path, args.query_images, tuple(args.query_sequences),
                           args.query_names)
    gt = {q.name: q.cam_from_world_gt for q in queries if q.cam_from_world_gt is not None}
    if not gt:
        raise ValueError("These queries have no ground truth to evaluate against.")
    records = read_records(args.output / "records.jsonl")
    thresholds = INDOOR_THRESHOLDS if args.indoor else DEFAULT_THRESHOLDS
    if args.preset:
        from . import presets
        thresholds = tuple(tuple(t) for t in presets.load(args.preset)["thresholds"])
    summary = evaluate(records, gt, thresholds)
    (args.output / "evaluation.json").write_text(json.dumps(summary, indent=1))
    print(format_summary(summary))
    return 0


def format_summary(summary) -> str:
    lines = []
    for key, s in summary.items():
        for which in ("prior", "refined"):
            r = s[which]
            recalls = "  ".join(f"{k[len('recall@'):]}: {v * 100:5.1f}%" for k, v in r.items()
                                if k.startswith("recall@"))
            lines.append(f"{key:<28} {which:<8} n={r['count']:<4} median {r['median_t']:.3f} / "
                         f"{r['median_R']:.2f} deg  {recalls}")
    return "\n".join(lines)


def add_report_arguments(p: argparse.ArgumentParser) -> None:
    add_query_arguments(p)
    p.add_argument("--output", type=Path, required=True, help="a pixloc localize output folder")
    p.add_argument("--examples", type=int, default=3, help="example queries shown")
    p.add_argument("--indoor", action="store_true", help="thresholds (5 cm, 5 deg)")
    p.set_defaults(func=report_main)


def report_main(args: argparse.Namespace) -> int:
    from .report import make_report
    queries = load_queries(args.query_kind, args.query_path, args.query_images, tuple(args.query_sequences),
                           args.query_names)
    path = make_report(args.output, queries, args.examples, INDOOR_THRESHOLDS if args.indoor else None)
    print(f"report: {path}")
    return 0
