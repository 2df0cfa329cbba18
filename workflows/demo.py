"""``pixloc demo``: the whole system on the embedded default, offline, in a few minutes.

1. generate a synthetic courtyard (a seed never used in training): reference views with depth
   along a path, queries from other viewpoints by day, at dusk, at night and with occluders;
2. build a map store from the depth and the known poses (points and the shipped model's
   features at their observations);
3. retrieve references per query by global descriptor among those of its area (a coarse
   location tag, as GPS gives; RobotCar practice) and take the top-1 pose as prior;
4. localize every query (Dask workers, or in-process with ``--sync``);
5. evaluate per condition, write ``report.html`` and print the summary.
"""

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Dict

from pipeline.evaluate import evaluate, evaluation_document, fmt, to_json
from pipeline.localization.refine import LocalizerConfig
from pipeline.localization.retrieval import GlobalDescriptors
from pipeline.localization.priors import PRIORS, Top1
from pipeline.localization.shard import LocalizationJob
from pipeline.data.synthetic import SyntheticConfig, ensure_generated, read_synthetic
from pipeline.textfiles import write_atomic

from . import executor, localize
from .demo_scene import DEMO_CAMERA, DEMO_SEED, DEMO_THRESHOLDS, MIN_REFERENCES, demo_map  # noqa: F401 (re-exported)
from .options import at_least
from .report import make_report

logger = logging.getLogger(__name__)


def _stage(k: int, text: str) -> float:
    print(f"[{k}/5] {text}", flush=True)
    return time.perf_counter()


def run_demo(output: Path, model: str = "pixloc-lite0", num_references: int = 30, queries_per_condition: int = 5,
             workers: int = 2, sync: bool = False, num_iters: int = 50, seed: int = DEMO_SEED,
             query_spread: float = 0.5, prior: str = Top1.name, client=None) -> Dict[str, Dict]:
    """Run the demo into ``output``; returns the evaluation summary (per condition)."""
    if num_references < MIN_REFERENCES:
        raise ValueError(f"--references {num_references}: the demo needs at least {MIN_REFERENCES} (its references "
                         "stand on a circle looking outwards; with fewer, no point is seen by three of them)")
    if queries_per_condition < 1:
        raise ValueError(f"--queries-per-condition {queries_per_condition}: at least 1")
    output = Path(output).resolve()  # recorded absolute in job.json
    t_start = _stage(1, f"generating the synthetic scene (seed {seed}): {num_references} references, "
                        f"{queries_per_condition} queries per condition")
    root = output / "scene"
    meta = root / "cameras.json"
    before = meta.stat().st_mtime_ns if meta.is_file() else None
    ensure_generated(root, SyntheticConfig(seed=seed), num_references, queries_per_condition, DEMO_CAMERA,
                     query_spread=query_spread)
    mapping, queries = read_synthetic(root)
    if before is not None and meta.stat().st_mtime_ns == before:
        print(f"      reused {root} (generated earlier with these settings)")

    t = _stage(2, f"building the map store from depth and known poses, features of {model}")
    store, fconf = demo_map(output, mapping, model, seed)

    job = LocalizationJob(str(store), fconf, model, LocalizerConfig(num_dbs=3, num_iters=num_iters),
                          GlobalDescriptors(k=5, same_tag="area"), prior=PRIORS.entry(prior)())
    t = _stage(3, f"retrieval and localization of {len(queries)} queries "
                  f"({'in-process' if sync else f'{workers} Dask workers'})")
    try:
        plan = localize.plan_localization(job, queries, output / "localization", workers=1 if sync else workers)
    except localize.AnotherRun as e:  # the demo's own folder, from another version or map: redone
        print(f"      {str(e).split(': use another --output')[0]}; the demo redoes it")
        plan = localize.plan_localization(job, queries, output / "localization", workers=1 if sync else workers,
                                          overwrite=True)
    plan.thresholds = DEMO_THRESHOLDS  # recorded in job.json: `pixloc evaluate` and `report` use them too
    if not plan.todo:
        records = localize.run_sync(plan)  # merges the finished shards, runs nothing
        print(f"      {len(records)} of {len(records)} queries already done in {plan.output}: nothing to do; "
              f"{sum(r['success'] for r in records)} of them refined and verified")
    else:
        records = localize.run_sync(plan, progress=True) if sync else _run_dask(plan, workers, client)
        print(f"      {sum(r['success'] for r in records)} of {len(records)} refined and verified in "
              f"{time.perf_counter() - t:.1f} s")

    _stage(4, "evaluation per condition")
    gt = {q.name: q.cam_from_world_gt for q in queries}
    summary = evaluate(records, gt, DEMO_THRESHOLDS, tag_keys=["condition"])
    # where `pixloc evaluate` writes it too: in the localization folder
    write_atomic(output / "localization" / "evaluation.json",
                 to_json(evaluation_document(summary, records, gt, DEMO_THRESHOLDS)))
    _stage(5, "report")
    report = make_report(output / "localization", queries, num_examples=3, thresholds=DEMO_THRESHOLDS, reuse=True)
    print()
    print(format_table(summary))
    print(f"\nreport: {report}\ntotal: {time.perf_counter() - t_start:.0f} s")
    return summary


def _run_dask(plan, workers: int, client=None):
    if client is not None:
        return localize.run_dask(plan, client, progress=True)
    with executor.dask_client(workers=workers, dashboard=False) as c:
        return localize.run_dask(plan, c, progress=True)


def format_table(summary: Dict[str, Dict]) -> str:
    keys = [k for k in summary["all"]["refined"] if k.startswith("recall@")]
    head = f"{'condition':<20} {'pose':<8} {'n':>3} {'median t':>9} {'median R':>9}  " + "  ".join(
        f"{k[len('recall@'):]:>11}" for k in keys)
    lines = [head, "-" * len(head)]
    for name, s in summary.items():
        for which, label in (("prior", "prior"), ("refined", "result")):
            r = s[which]
            lines.append(f"{name:<20} {label:<8} {r['count']:>3} {fmt(r['median_t'], '>8.3f')}m "
                         f"{fmt(r['median_R'], '>7.2f')}deg  "
                         + "  ".join(f"{fmt(100 * r[k] if r[k] is not None else None, '>10.0f')}%" for k in keys))
    lines.append("result: the refined pose where verification accepted it, else the prior (docs/verification.md)")
    return "\n".join(lines)


OWN_INPUTS = [name for name, entry in PRIORS.items() if not entry.inputs]  # the demo's scene has no files for others


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--output", type=Path, default=Path("outputs/demo"), help="output folder (default outputs/demo)")
    p.add_argument("--model", default="pixloc-lite0", help="feature model (default: the shipped pixloc-lite0)")
    p.add_argument("--references", type=at_least(1), default=30,
                   help=f"map images of the synthetic scene (at least {MIN_REFERENCES})")
    p.add_argument("--queries-per-condition", type=at_least(1), default=5,
                   help="queries of each condition (day, dusk, night, occluded)")
    p.add_argument("--workers", type=at_least(1), default=2, help="Dask workers (processes)")
    p.add_argument("--sync", action="store_true", help="localize in this process, without Dask")
    p.add_argument("--prior", choices=OWN_INPUTS, default=Top1.name,
                   help="pose prior of the localization (see pixloc localize --help; sift: SIFT + PnP, refined)")
    p.add_argument("--rig", action="store_true",
                   help="instead: a three-camera rig at the query poses of each condition, localized as one body "
                        "beside its images one by one (pixloc benchmark rigs; in-process)")
    p.set_defaults(func=main)


def run_rig_demo(output: Path, model: str, num_references: int, queries_per_condition: int) -> Dict:
    """``pixloc demo --rig``: the demo's scene and map in ``output``, and the rig benchmark on them."""
    from .benchmarks import rigs
    if num_references < MIN_REFERENCES:
        raise ValueError(f"--references {num_references}: the demo needs at least {MIN_REFERENCES}")
    print(f"a three-camera rig at {queries_per_condition} query poses per condition, each frame localized as one "
          "body, and its images one by one (in-process)", flush=True)
    out = rigs.run(Path(output).resolve(), queries_per_condition, model, num_references, queries_per_condition)
    print()
    print(rigs.format_table(out))
    path = Path(output) / "rigs.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"\nwritten: {path}")
    return out


def main(args: argparse.Namespace) -> int:
    if args.rig:
        if args.prior != Top1.name:
            raise ValueError(f"--rig --prior {args.prior}: a rig frame starts from its images' top-1 references "
                             f"(--prior {Top1.name}); the other priors are not there yet for rigs")
        run_rig_demo(args.output, args.model, args.references, args.queries_per_condition)
        return 0
    run_demo(args.output, args.model, args.references, args.queries_per_condition, args.workers, args.sync,
             prior=args.prior)
    return 0
