"""Benchmark: queries per second, stored reference features (ours) vs the official way.

The official PixLoc localizer re-extracts the dense features of every
reference image for every query (base_refiner.py: "TODO: can we compute this
offline before hand?"); ours reads them from the map store. Both run the
same refinement at the Cambridge settings (5 references, image scales
[4, 1], observations averaged, 100 LM iterations per level) on a map of the
Sacre Coeur (the oracle's SfM model), two queries per task on a LocalCluster whose
workers have imported the pipeline and loaded the network before the clock starts.
"""

import argparse
from dataclasses import replace
import resource
import shutil
import tempfile
import time
from pathlib import Path

from pipeline.runtime import shared_folder
from pipeline.mapping.build import build_map
from pipeline.mapping.features import FeatureConfig
from pipeline.localization.refine import LocalizerConfig
from pipeline.queries import read_queries_with_intrinsics
from pipeline.textfiles import read_pairs
from pipeline.mapping.readers.colmap import read_colmap
from pipeline.localization.retrieval import PairsFile
from pipeline.localization.shard import LocalizationJob

from .. import executor
from ..localize import plan_localization, run_dask


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shared", type=Path, default=shared_folder(),
                   help="the shared data folder (default: $PIXLOC_SHARED, else ../shared)")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to compare")
    p.add_argument("--iters", type=int, default=100, help="LM iterations per level")
    p.add_argument("--resize", type=int, default=1024, help="longer image side of the features")
    p.add_argument("--repeat", type=int, default=4, help="copies of the 3 oracle queries (fixed costs amortise)")


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _warm_up(model: str) -> None:
    """Import the pipeline and load the network in a worker, so that both ways are timed
    in steady state (process start and model loading are one-off costs, the same for both)."""
    from pipeline.models import network
    from pipeline.models import localization_model
    localization_model(model)
    network(model)


def official_way_shard(job: LocalizationJob, queries, out_path, images_root: str):
    """The official localizer's data flow: for every query, re-extract its references'
    features (into a private store), then localize from them. Extraction and sampling are
    the same code as ours; the private store adds a few ms of zarr I/O per image."""
    from pipeline.localization.results import write_records
    from pipeline.localization.shard import localize_shard
    scene = read_colmap(Path(job.store).parent / "sfm", images_root)
    pairs = read_pairs(job.retrieval.pairs)
    records = []
    for query in queries:
        tmp = Path(tempfile.mkdtemp())
        try:
            refs = set(pairs[query.name][:job.localizer.num_dbs])
            keep = [i for i, im in enumerate(scene.images) if im.name in refs]
            build_map(scene.subset(keep), tmp / "refs.zarr", job.features)
            records += localize_shard(replace(job, store=str(tmp / "refs.zarr")), [query], tmp / "out.jsonl")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    write_records(records, out_path)
    return records


def main(args: argparse.Namespace) -> int:

    oracle = args.shared / "oracle"
    images = args.shared / "data" / "sacre_coeur" / "mapping"
    work = Path(tempfile.mkdtemp())
    try:
        scene = read_colmap(oracle / "sacre_coeur_sfm", images)
        shutil.copytree(oracle / "sacre_coeur_sfm", work / "sfm")
        fconf = FeatureConfig(resize=args.resize, image_scales=(4, 1), dtype="float16")
        t0 = time.perf_counter()
        build_map(scene, work / "map.zarr", fconf)
        build_s = time.perf_counter() - t0
        base = read_queries_with_intrinsics(oracle / "queries_with_intrinsics.txt", images)
        pairs = read_pairs(oracle / "pairs.txt")
        queries = [replace(q, name=f"{k}/{q.name}") for k in range(args.repeat) for q in base]
        (work / "pairs.txt").write_text("".join(f"{k}/{q.name} {r}\n" for k in range(args.repeat) for q in base
                                                for r in pairs[q.name]))
        job = LocalizationJob(str(work / "map.zarr"), fconf, fconf.model,
                              LocalizerConfig(num_dbs=5, average_observations=True, num_iters=args.iters),
                              PairsFile(pairs=str(work / "pairs.txt")))
        print(f"Localization, Cambridge settings, {len(queries)} queries ({len(base)} oracle queries x "
              f"{args.repeat}) on a {len(scene.images)}-image map "
              f"(built once in {build_s:.1f} s), {args.iters} LM iterations per level")
        print(f"{'workers':>7} {'official q/s':>13} {'ours q/s':>9} {'ours/official':>14} "
              f"{'peak MiB/worker (official, ours)':>33}")
        for workers in args.workers:
            rates = {}
            peaks = {}
            for way in ("official", "ours"):
                with executor.dask_client(workers=workers, dashboard=False) as client:
                    plan = plan_localization(job, queries, work / f"{way}-{workers}", shard_size=2)
                    client.run(_warm_up, job.model)
                    t0 = time.perf_counter()
                    if way == "ours":
                        run_dask(plan, client)
                    else:
                        plan.shard_path(0).parent.mkdir(parents=True, exist_ok=True)
                        futures = [client.submit(official_way_shard, job, plan.shards[k], str(plan.shard_path(k)),
                                                 str(images), pure=False) for k in plan.pending()]
                        client.gather(futures)
                    rates[way] = len(queries) / (time.perf_counter() - t0)
                    peaks[way] = max(client.run(_peak_rss_mib).values())
            print(f"{workers:>7} {rates['official']:>13.3f} {rates['ours']:>9.3f} "
                  f"{rates['ours'] / rates['official']:>13.2f}x {peaks['official']:>16.0f}, {peaks['ours']:.0f}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0
