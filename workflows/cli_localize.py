"""``pixloc localize``, ``pixloc evaluate`` and ``pixloc report``.

The job's options (``FLAGS``) are fields of ``LocalizationJob``: its dataclasses hold the defaults,
a preset and then the command line override them (``workflows.options``). Every path is
resolved once, here, and recorded absolute.
"""

import argparse
import logging
import time
from collections import Counter
from pathlib import Path
from dataclasses import asdict
from typing import Dict, Optional

import numpy as np

from pipeline.evaluate import (DEFAULT_THRESHOLDS, INDOOR_THRESHOLDS, evaluate, evaluation_document, fmt,
                               parse_thresholds, recall_label, shown_families, to_json)
from pipeline.progress import count
from pipeline.runtime import BFLOAT16_FLAGS, native_bfloat16
from pipeline.localization.results import POSE_NAMES, REJECTED, outcome, pose_names_problem, read_records, reason_groups
from pipeline.localization.priors import PRIORS, Top1
from pipeline.localization.retrieval import RETRIEVERS
from pipeline.localization.shard import LocalizationJob
from pipeline.mapping.readers.sources import SOURCES, load_queries, map_units, query_kinds
from pipeline.store import location
from pipeline.store.info import feature_config, level_count, map_images, map_source
from pipeline.store.layout import StoreError
from pipeline.textfiles import read_json, write_atomic
from pixloc.nets.unet import NETWORK_PRECISIONS

from . import executor
from .options import Flag, add_flags, at_least, build, given
from .localize import ORDERS, REGION_MIN_QUERIES, plan_localization, run_dask, run_sync

logger = logging.getLogger(__name__)

# the job's command-line options: the field each sets and what it means; the type, choices and
# default come from the dataclass (``workflows.options``), so a new option is its field and one line
FLAGS = {
    "--retrieval": Flag("retrieval", "how the references are found: " + "; ".join(
        f"{name}: {entry.help}" for name, entry in RETRIEVERS.items()) + " (default: the method whose option is "
        "given, else global)", tuple(RETRIEVERS)),
    "--retrieval-k": Flag("retrieval.k", "references retrieved"),
    "--same-tag": Flag("retrieval.same_tag", "restrict references to those sharing this tag with the query"),
    "--prior": Flag("prior", "pose prior: " + "; ".join(f"{name}: {entry.help}" for name, entry in PRIORS.items())
                    + f" (default {Top1.name})", tuple(PRIORS)),
    "--min-points": Flag("localizer.min_points", "fewer 3D points fails a query (official; 100 in refinement mode)"),
    "--min-track-length": Flag("localizer.min_track_length", "leave out points seen by fewer map images (official; "
                               "2 keeps the points of two-view maps)"),
    "--points-per-cell": Flag("localizer.points_per_cell", "at levels with more points than this many per query "
                              "feature-map cell, LM runs on a seeded subset (at least 1024 points; 0: all, official; "
                              "the 7scenes preset: 1)"),
    "--levels": Flag("levels", "optimise only these levels (refinement mode: 0 1; default all)"),
    "--scales": Flag("scales", "run only these of the store's image scales (refinement mode: 1; default all)"),
    "--num-dbs": Flag("localizer.num_dbs", "reference images per query"),
    "--average-observations": Flag("localizer.average_observations", "one residual per point, confidence-weighted "
                                   "over references"),
    "--iters": Flag("localizer.num_iters", "LM iterations per level"),
    "--min-confidence": Flag("localizer.verification.min_confidence", "verification: refinements with a lower "
                             "confidence are rejected and keep their prior (docs/verification.md)"),
    "--max-turn": Flag("localizer.verification.max_move_R", "verification: a refinement that turns the camera more "
                       "than this many degrees from its prior is rejected"),
    "--max-sigma": Flag("localizer.verification.max_sigma", "verification: a refinement whose pose the cost pins "
                        "down less (standard deviation along its least-determined direction, in 1 %% of the depth "
                        "and 1 deg) is rejected (0: no limit)"),
    "--rivals": Flag("localizer.verification.rivals", "verification: other references' poses refined to check a pose "
                     "refined from a map pose; one verified elsewhere rejects it as ambiguous (0: no check)"),
    "--rival-join": Flag("localizer.verification.join", "verification: a rival stops at a coarser level where it "
                         "lies within this fraction of the agreement thresholds of the query's start (0: never)"),
    "--rival-sharper-by": Flag("localizer.verification.sharper_by", "verification: a rival verified elsewhere does "
                               "not reject a pose whose cost is this many times sharper (3 px contrast) than the "
                               "rival's (0: every such rival rejects it)"),
    "--max-keypoint-chi2": Flag("localizer.verification.max_keypoint_chi2", "verification: where a start comes "
                                "from PnP, a refined pose that raises its inliers' chi-square by more than this is "
                                "replaced by the PnP pose (e.g. 16.8: the 0.99 quantile of 6 degrees of freedom; "
                                "default 0: never)"),
    "--no-verify": Flag("localizer.verification.enabled", "report every converged refinement as a success (official "
                        "PixLoc behaviour)", value=False),
    "--network-precision": Flag("localizer.network_precision", "the query's network pass in bfloat16 (a query's CPU "
                                "time 0.8x on a CPU with AVX512-BF16, other poses), or bfloat16-fine: only the "
                                "blocks that the finest level alone reads (0.84-0.88x, the same recall, poses "
                                "up to 0.4 mm and 0.3 deg apart); CPUs without native bfloat16 may be slower; "
                                "the LM stays float32",
                                tuple(NETWORK_PRECISIONS)),
    "--device": Flag("device", "torch device of the network and the LM (cpu, cuda)"),
}


def absolute(path) -> Optional[Path]:
    """A command-line path made absolute, once, here (None stays None)."""
    return Path(path).expanduser().resolve() if path is not None else None


def _absolute(path) -> Optional[str]:
    """``absolute`` as the string that jobs record."""
    return str(absolute(path)) if path is not None else None


def add_query_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("query_kind", choices=query_kinds(), help="where the queries come from: " + "; ".join(
        f"{kind}: {SOURCES[kind].help}" for kind in query_kinds()))
    p.add_argument("query_path", type=Path, help="query list file, or dataset root")
    p.add_argument("--query-images", "--images", type=Path, help="image folder of a query list, COLMAP model, Bundler "
                   "bundle or OpenSfM reconstruction (--images, as build-map names it, is the same)")
    p.add_argument("--query-sequences", type=int, nargs="+", default=[],
                   help="7scenes queries: the sequences to localize (official test split: 1 4)")
    p.add_argument("--intrinsics", type=float, nargs=4, default=[], metavar=("FX", "FY", "CX", "CY"),
                   help="posetxt queries: the colour camera's intrinsics (COLMAP convention), as build-map's")
    p.add_argument("--query-names", nargs="+", help="keep only these queries")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_query_arguments(p)
    p.add_argument("--store", required=True, help="map store built by pixloc build-map (a folder or a URL: "
                   "s3://bucket/map.zarr)")
    p.add_argument("--features", help="feature group of the store (default: its only one)")
    p.add_argument("--output", type=Path, required=True, help="output folder (records, poses, shards)")
    add_job_flags(p)
    p.add_argument("--pose-names", choices=POSE_NAMES, help="also write poses_NAMES.txt with these names for a "
                   "benchmark submission: basename (Aachen, CMU) or camera (parentdir/basename: RobotCar, 7-Scenes, "
                   "Cambridge); poses.txt always has the full names (default: the preset's, else none)")
    p.add_argument("--shard-size", type=int, help="queries per task (default: a rerun keeps its own; a new run "
                   "takes enough tasks for every worker to get several, at most 8 queries each)")
    p.add_argument("--order", choices=list(ORDERS), default="auto",
                   help="how queries are sharded: region (by the map region of their top-1 reference, after a "
                        "retrieval stage: each worker reads a bounded part of the store; with the store's global "
                        "descriptors that stage runs the network once more per query), list (query order), or "
                        f"auto (default: region from {REGION_MIN_QUERIES} queries with --pairs or --descriptors, "
                        "else list)")
    p.add_argument("--scheduler", help="an existing Dask scheduler: its address (tcp://host:8786) or the file "
                   "that 'dask scheduler "
                   "--scheduler-file' wrote (default: a local cluster; docs/cluster.md)")
    p.add_argument("--workers", type=int, default=2, help="worker processes of the local cluster (default 2)")
    p.add_argument("--sync", action="store_true", help="run in this process, without Dask")
    p.add_argument("--keep-failures", action="store_true",
                   help="a rerun keeps earlier failures instead of retrying them")
    p.add_argument("--overwrite", action="store_true", help="redo a run whose output folder holds another job, "
                   "or results against another map")
    p.add_argument("--allow-partial-map", action="store_true", help="localize against a store whose build has "
                   "not finished (refused by default: the results would change as the build goes on)")
    p.add_argument("--ground-truth", type=Path, help="ground-truth poses file (name qw qx qy qz tx ty tz, "
                   "cam_from_world): the accuracy table is printed after the run")
    p.add_argument("--rigs", type=Path, help="rig file: 'rig_id sensor_id qw qx qy qz tx ty tz' per camera "
                   "(cam_from_rig; kapture's rigs.txt reads as is); with --rig-frames, the images of a rig frame are "
                   "localized as one body (docs/localize.md, 'Rigs and sequences')")
    p.add_argument("--rig-frames", type=Path, help="frames file: 'image_name rig_id frame_id sensor_id' per query "
                   "image of a rig (queries it does not name are localized alone)")
    p.add_argument("--odometry", type=Path, help="odometry file of a sequence: 'image_name qw qx qy qz tx ty tz' "
                   "(cam_from_odom) per frame, in the order taken; its chunks of --chunk frames are localized as "
                   "one body each (docs/localize.md, 'Rigs and sequences')")
    p.add_argument("--chunk", type=at_least(1), help="frames per chunk of an --odometry sequence (default 5)")
    p.add_argument("--dry-run", action="store_true", help="print the plan and exit; writes nothing")
    p.add_argument("--preset", help="dataset preset with the paper's settings: " + ", ".join(presets_available()))
    p.set_defaults(func=main)


def presets_available():
    from . import presets
    return presets.available()


CHOOSERS = ("--retrieval", "--prior")  # the options that choose a registry entry: their values are names


def entry_prefix(registry, name: str) -> str:
    """Where an entry's own options land in the parsed arguments."""
    return f"{registry.axis}:{name}."


def add_job_flags(p: argparse.ArgumentParser) -> None:
    """The job's options: its own fields', the entry choices, and each retrieval method's and
    prior's own options (from the registries)."""
    for flag in CHOOSERS:
        p.add_argument(flag, dest=FLAGS[flag].path, choices=list(FLAGS[flag].choices), help=FLAGS[flag].help)
    add_flags(p, LocalizationJob, {k: f for k, f in FLAGS.items() if k not in CHOOSERS})
    for registry in (RETRIEVERS, PRIORS):
        for name, entry in registry.items():
            add_flags(p, entry, entry.flags, prefix=entry_prefix(registry, name))


def chosen(registry, name: Optional[str], cli: Dict, preset: Dict, where: str):
    """The settings of the entry ``name`` of ``registry`` (None: the one whose own options the
    command line gives, else the preset's, else the default): its fields from the preset's block
    of that name, then the command line. Options of another entry are refused."""
    own = {n: given(cli, e.flags, entry_prefix(registry, n)) for n, e in registry.items()}
    used = [n for n, values in own.items() if values]
    if name is None and len(used) == 1:
        name = used[0]
    name = name or preset.get(registry.axis, {}).get("name") or next(iter(registry))
    entry = registry.entry(name)
    other = [n for n in used if n != name]
    if other:
        flags = [f for f, flag in registry[other[0]].flags.items() if flag.path in own[other[0]]]
        raise ValueError(f"{', '.join(flags)}: an option of the {registry.axis} {other[0]}, not of {name}.")
    values = {**preset.get(registry.axis, {}).get(name, {}), **own[name]}
    return build(entry, {k: v for k, v in values.items() if k != "name"}, where=f"{where} ({registry.axis} {name})")


def prior_options(args: argparse.Namespace, prior) -> Dict:
    """{option: value} of the prior's own options that the command line gives."""
    values = given(args, prior.flags, entry_prefix(PRIORS, prior.name))
    return {flag: values[f.path] for flag, f in prior.flags.items() if f.path in values}


def job_settings(args: argparse.Namespace) -> Dict:
    """The job's fields set by the preset and then the command line (by dotted path; the retrieval
    and the prior as their entries' settings)."""
    from . import presets
    cli = given(args, {k: f for k, f in FLAGS.items() if k not in CHOOSERS})
    preset = presets.load(args.preset) if args.preset else None
    prior_name = args.prior
    settings, blocks = presets.job_settings(preset, prior_name)
    settings.update(cli)
    prior = chosen(PRIORS, prior_name, args, blocks, "localize options")
    retrieval = chosen(RETRIEVERS, args.retrieval, args, blocks, "localize options")
    shared = {k.split(".", 1)[1]: settings.pop(k) for k in list(settings) if k.startswith("retrieval.")}
    retrieval = build(type(retrieval), {**asdict(retrieval), **shared}, where="localize options")
    return {**settings, "retrieval": retrieval, "prior": prior}


def pose_names_of(args: argparse.Namespace) -> str:
    """--pose-names, else the preset's, else only the full names."""
    from . import presets
    if args.pose_names:
        return args.pose_names
    return (presets.load(args.preset).get("pose_names") if args.preset else None) or POSE_NAMES[0]


def build_job(args: argparse.Namespace) -> LocalizationJob:
    """The job: the store and its features, the dataclass defaults, the preset, the command line."""
    store = location.normalize(args.store)
    fconf = feature_config(store, args.features)
    settings = job_settings(args)
    if settings.get("scales") and not set(settings["scales"]) <= set(fconf.image_scales):
        raise ValueError(f"--scales {settings['scales']}: the store's features have image scales "
                         f"{list(fconf.image_scales)}.")
    prior = settings["prior"]
    levels = [("--levels", settings["levels"])] if settings.get("levels") else []
    levels += [(flag, value) for flag, value in prior_options(args, prior).items() if flag.endswith("-levels")]
    if levels:  # before: every query failed with levels the store does not have
        n = level_count(store, fconf)
        for flag, wanted in levels:
            if not set(wanted) <= set(range(n)):
                raise ValueError(f"{flag} {list(wanted)}: the store's features have levels 0 (finest) to {n - 1}.")
    rigs = {"rigs": _absolute(args.rigs), "rig_frames": _absolute(args.rig_frames)} if args.rigs or args.rig_frames \
        else {}
    if args.chunk is not None and not args.odometry:
        raise ValueError("--chunk cuts an --odometry sequence into chunks: give --odometry too.")
    if args.odometry:
        rigs.update(odometry=_absolute(args.odometry), chunk=args.chunk or LocalizationJob.chunk)
    job = build(LocalizationJob, {"store": str(store), "features": fconf, "model": fconf.model, **rigs}, settings,
                where="localize options")
    job.validate()
    return job


def _load_queries(args):
    return load_queries(args.query_kind, absolute(args.query_path), absolute(args.query_images),
                        tuple(args.query_sequences), args.query_names, tuple(args.intrinsics))


def main(args: argparse.Namespace) -> int:
    output = Path(_absolute(args.output))
    if output.exists() and not output.is_dir():
        raise ValueError(f"--output {output} is a file: the run's outputs go in a folder.")
    job = build_job(args)
    queries = _load_queries(args)
    gt = ground_truth(args, queries)  # read before the run: a bad file fails now, not after it
    plan = plan_localization(job, queries, output, args.shard_size, workers=1 if args.sync else args.workers,
                             keep_failures=args.keep_failures, overwrite=args.overwrite, order=args.order,
                             allow_partial_map=args.allow_partial_map)
    pose_names = pose_names_of(args)
    problem = pose_names_problem([q.name for q in queries], pose_names)
    if problem:
        raise ValueError(problem[0].upper() + problem[1:] + ".")
    plan.pose_names = pose_names
    plan.thresholds = preset_thresholds(args.preset)
    print(plan.describe())
    if not args.dry_run:
        from .logs import to_file
        print(f"  log     {to_file(output / 'pixloc.log')}")
        logger.info("job %s", job.to_dict())
    precision = job.localizer.network_precision
    if precision != "float32" and job.device == "cpu" and native_bfloat16() is False:
        print(f"warning: --network-precision {precision}: this CPU has no native bfloat16 (neither "
              f"{' nor '.join(BFLOAT16_FLAGS)} among its flags), so the network pass is emulated and may be slower "
              "than in float32")
    both = queries_in_map(job.store, queries)
    if both:
        print(f"warning: {len(both)} of the {len(queries)} queries are also map images (the same name or the same "
              f"bytes: {', '.join(both[:3])}{' ...' if len(both) > 3 else ''}); such a query retrieves itself and "
              "its accuracy says nothing: hold it out of the map")
    if args.dry_run:
        return 0
    counts = plan.counts()
    t0 = time.time()
    if not plan.todo:
        print(f"{counts['queries']} of {counts['queries']} queries already done in {output}: nothing to do "
              "(--overwrite redoes them).")
        records = run_sync(plan)  # merges the finished shards (poses.txt, failed.txt) and nothing else
    else:
        records = executor.run_plan(plan, run_sync, run_dask, sync=args.sync, scheduler=args.scheduler,
                                    workers=args.workers, device=job.device)
    by = Counter(outcome(r) for r in records)
    ran = (f"{counts['to_run']} run in {time.time() - t0:.1f} s, {counts['reused_queries']} reused" if counts["to_run"]
           else "all reused")
    print(f"\n{count(len(records), 'query')} ({ran}): {by['refined']} refined, {by['rejected']} rejected by "
          "verification, "
          f"{by['failed']} failed; poses.txt has the prior of those without a verified pose, where they have "
          f"one.\n  -> {output / 'poses.txt'}, "
          f"{output / 'kapture'}, {output / 'failed.txt'}, {output / 'records.jsonl'}"
          + (f", {output / f'poses_{plan.pose_names}.txt'}" if plan.pose_names != "full" else ""))
    for kind, _, group in reason_groups(records)[:5]:  # reasons that differ only in their figures count as one
        reason = group[0]["reason"].removeprefix(REJECTED)
        print(f"  {len(group)} {kind}: {reason}" + (f" (and {len(group) - 1} like it)" if len(group) > 1 else ""))
    io = store_io(records)
    if io:
        print(f"  map store reads: {io['bytes_per_query'] / 2**20:.2f} MiB per query, {io['blocks']} reference "
              f"blocks read, block-cache hit rate {100 * io['hit_rate']:.0f} % (per worker process)")
    dropped = Counter()
    for r in records:
        dropped.update(r.get("filters", {}))
    if dropped:
        print(f"  point filters, over all queries: {dropped['short_tracks']} points seen by fewer than "
              f"{job.localizer.min_track_length} map images left out (--min-track-length), "
              + ", ".join(f"{v} observations invalid at image scale index {k.rsplit('_s', 1)[1]}"
                          for k, v in dropped.items() if k.startswith("invalid_observations")))
    if any(T is not None for T in gt.values()):
        print("\n" + format_summary(evaluate(records, gt, plan.thresholds), store_units(job.store)))
    return 0


def store_io(records) -> Optional[Dict]:
    """Store reads of the run's shards (each record carries its shard's): bytes per query, blocks
    read and the hit rate of the workers' block caches."""
    with_io = [r["store_io"] for r in records if r.get("store_io")]
    if not with_io:
        return None
    share = [1 / max(x["shard_queries"], 1) for x in with_io]  # each shard counted once
    total = {k: sum(x[k] * w for x, w in zip(with_io, share)) for k in ("bytes_read", "blocks_read", "cache_hits")}
    lookups = total["blocks_read"] + total["cache_hits"]
    return {"bytes_per_query": total["bytes_read"] / len(with_io), "blocks": round(total["blocks_read"]),
            "hit_rate": total["cache_hits"] / lookups if lookups else 0.0}


def add_evaluate_arguments(p: argparse.ArgumentParser) -> None:
    add_query_arguments(p)
    p.add_argument("--output", type=Path, required=True, help="a pixloc localize output folder")
    add_threshold_arguments(p)
    p.add_argument("--ground-truth", type=Path, help="ground-truth poses file (name qw qx qy qz tx ty tz, "
                   "cam_from_world), for query lists that carry none")
    p.set_defaults(func=evaluate_main)


def add_threshold_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--thresholds", nargs="+", metavar="DIST,DEG",
                   help="recall thresholds, e.g. 0.05,1 0.25,2 (scene units, degrees)")
    p.add_argument("--indoor", action="store_true", help="thresholds (5 cm, 5 deg) as for 7-Scenes/Cambridge")
    p.add_argument("--preset", help="take the dataset preset's thresholds")


def thresholds_of(args: argparse.Namespace, recorded=None):
    """--thresholds, else the preset's, else --indoor's, else ``recorded`` (those the run recorded
    in its job.json: ``recorded_job``), else the defaults."""
    if args.thresholds:
        return parse_thresholds(args.thresholds)
    if args.preset:
        return preset_thresholds(args.preset)
    if args.indoor:
        return INDOOR_THRESHOLDS
    return tuple(tuple(float(x) for x in t) for t in recorded) if recorded else DEFAULT_THRESHOLDS


def preset_thresholds(preset: Optional[str]):
    """A dataset preset's recall thresholds (the defaults without one)."""
    if not preset:
        return DEFAULT_THRESHOLDS
    from . import presets
    return tuple(tuple(t) for t in presets.load(preset)["thresholds"])


def recorded_job(output: Path) -> Dict:
    """The job.json of a localize output folder ({} where there is none)."""
    path = Path(output) / "job.json"
    return read_json(path, "job file") if path.is_file() else {}


def ground_truth(args: argparse.Namespace, queries) -> Dict[str, Optional[np.ndarray]]:
    """The queries' ground truth (None where they have none), or that of ``--ground-truth``."""
    if args.ground_truth is not None:
        from pipeline.textfiles import read_poses, warn_partial_matches
        poses = read_poses(_absolute(args.ground_truth))  # strict: file:line for a bad line or a duplicate
        warn_partial_matches(poses, [q.name for q in queries], "check that they are the same images")
        gt = {q.name: poses.find(q.name) for q in queries}
        missing = [name for name, T in gt.items() if T is None]  # before: left out of the evaluation without a word
        if missing and len(missing) == len(gt):
            raise ValueError(f"--ground-truth {args.ground_truth}: no pose for any of the {len(gt)} queries (e.g. "
                             f"{missing[0]}; the file has {len(poses)} poses).")
        if missing:
            logger.warning("--ground-truth %s: %d of the %d queries have no pose there and are not evaluated "
                           "(e.g. %s)", args.ground_truth, len(missing), len(gt), missing[0])
        return gt
    return {q.name: q.cam_from_world_gt for q in queries}


def evaluate_main(args: argparse.Namespace) -> int:
    queries = _load_queries(args)
    gt = ground_truth(args, queries)
    if all(T is None for T in gt.values()):
        raise ValueError("These queries have no ground truth to evaluate against: pass --ground-truth POSES.")
    records = read_records(args.output / "records.jsonl")
    run = recorded_job(args.output)
    thresholds = thresholds_of(args, run.get("thresholds"))
    summary = evaluate(records, gt, thresholds)
    write_atomic(args.output / "evaluation.json", to_json(evaluation_document(summary, records, gt, thresholds)))
    print(format_summary(summary, store_units(run["job"]["store"]) if "job" in run else "scene units"))
    return 0


def queries_in_map(store, queries) -> list:
    """The queries that are also images of the store's map (``pipeline.queries.also_in_map``)."""
    from pipeline.queries import also_in_map
    images = map_images(store)
    return also_in_map(queries, [im.name for im in images], [im.path for im in images])


def store_units(store) -> str:
    """The distance unit of a store's map (``pipeline.mapping.readers.sources.map_units`` of its source)."""
    try:
        return map_units(map_source(store))
    except StoreError:  # the store was moved since the run: its unit is unknown
        return "scene units"


def format_summary(summary, units: str = "m", group_by=None) -> str:
    """The accuracy table for the terminal: ``all``, then the tag families worth a row each
    (``pipeline.evaluate.shown_families``; ``group_by`` chooses them)."""
    lines = []
    missing = summary["all"].get("no_ground_truth", 0)
    shown = {"all"} | {k for keys in shown_families(summary, group_by).values() for k in keys}
    for key, s in summary.items():
        if key not in shown:
            continue
        for which, label in (("prior", "prior"), ("refined", "result")):
            r = s[which]
            recalls = "  ".join(f"{recall_label(k, units)}: {fmt(100 * v if v is not None else None, '5.1f')}%"
                                for k, v in r.items() if k.startswith("recall@"))
            lines.append(f"{key:<28} {label:<8} n={r['count']:<4} median {fmt(r['median_t'], '.3f')} / "
                         f"{fmt(r['median_R'], '.2f')} deg  {recalls}")
    lines.append("result: the refined pose where verification accepted it, else the prior")
    if missing:
        lines.append(f"({missing} queries without ground truth not evaluated)")
    return "\n".join(lines)


def add_report_arguments(p: argparse.ArgumentParser) -> None:
    add_query_arguments(p)
    p.add_argument("--output", type=Path, required=True, help="a pixloc localize output folder")
    p.add_argument("--examples", type=at_least(0), default=3, help="example queries per condition: best, median, worst "
                   "(default 3), then up to 3 failures")
    p.add_argument("--units", help="distance unit of the map (default: m for metric sources, 'SfM units' for SfM "
                   "models)")
    add_threshold_arguments(p)
    p.add_argument("--ground-truth", type=Path, help="ground-truth poses file, for query lists that carry none")
    p.add_argument("--group-by", nargs="+", metavar="TAG", help="tabulate accuracy by these tag families (default: "
                   "every family but those with one value for all queries or one query per value)")
    p.set_defaults(func=report_main)


def report_main(args: argparse.Namespace) -> int:
    from .report import make_report
    queries = _load_queries(args)
    gt = ground_truth(args, queries)
    output = absolute(args.output)
    thresholds = thresholds_of(args, recorded_job(output).get("thresholds"))
    path = make_report(output, queries, args.examples, thresholds, ground_truth=gt, units=args.units,
                       group_by=args.group_by)
    print(f"report: {path}")
    return 0
