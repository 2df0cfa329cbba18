"""The processes that the scale benchmarks start, each measured on its own (its own peak memory,
its own Python and torch state): ``python -m workflows.benchmarks.drivers NAME ARGS...``; each
prints its figures as one JSON line.

- ``city ROOT STORE OUT SCHED LIMIT ORDER WARM``: localize a generated city's queries through
  the Dask scheduler of ``SCHED`` (a scheduler file), or in-process for ``sync:K/N`` (slice K of
  N, no Dask); ``WARM`` 1 loads the network and opens the store first (``city_run``).
- ``read STORE CONF QUERIES SEED``: open a store and read the observations and features of
  ``QUERIES`` random 3-image windows (``scale``: open time, read latency, memory).
- ``localize ROOT STORE OUT [POINTS_PER_CELL [PRIOR [ITERS]]]``: localize a generated scene's queries
  in-process (``scale``: time and memory per query, recall, bytes read; the prior, default top1, and the LM
  iterations per level, default 30, for experiments).
"""

import json
import sys
import time
from pathlib import Path
from typing import Callable, Dict, List

import numpy as np
from pipeline.localization.priors import Top1

CITY_THRESHOLDS = ((0.25, 2.0), (1.0, 5.0))  # (m, deg): the city's recall, the first also its wrong accepted poses


def peak_rss() -> int:
    """This process's peak resident memory (ru_maxrss would include the parent's, kept across exec)."""
    return int(Path("/proc/self/status").read_text().split("VmHWM:")[1].split()[0]) * 1024


def rss() -> int:
    return int(Path("/proc/self/status").read_text().split("VmRSS:")[1].split()[0]) * 1024


def _job(store: str, points_per_cell: float = 0.0, prior: str = Top1.name, num_iters: int = 30):
    """The benchmarks' localization job: 3 references, 30 LM iterations, retrieval within the area;
    ``points_per_cell`` as the localizer's (1 for the dense maps of the photo city); another ``prior`` or
    ``num_iters`` per level for the S2 driver's experiments."""
    from pipeline.localization.refine import LocalizerConfig
    from pipeline.localization.retrieval import GlobalDescriptors
    from pipeline.localization.priors import PRIORS
    from pipeline.localization.shard import LocalizationJob
    from pipeline.store.info import feature_config as store_feature_config
    conf = store_feature_config(Path(store))
    return LocalizationJob(store, conf, conf.model, LocalizerConfig(num_dbs=3, num_iters=num_iters,
                                                                    points_per_cell=points_per_cell),
                           GlobalDescriptors(k=5, same_tag="area"), prior=PRIORS.entry(prior)())


def warm_up(job) -> None:
    """Load the network and open the map in this (worker) process: one-off costs of a worker's first
    task, which P3 leaves out so that it compares the steady-state rates of 1 and 2 workers."""
    from pipeline.store.reader import open_reader
    from pipeline.models import localization_model
    _, digest = localization_model(job.model, job.device)
    open_reader(job.store, job.features, digest)


def city(root: str, store: str, out: str, sched: str, limit: str, order: str, warm: str) -> None:
    from pipeline.data.synthetic import read_synthetic
    from workflows.localize import plan_localization, run_dask, run_sync
    _, queries = read_synthetic(root)
    queries = sorted(queries, key=lambda q: q.name)[:int(limit) or None]
    job = _job(store)
    if sched.startswith("sync:"):  # a bare process: its slice of the queries, in-process, no Dask
        part, parts = map(int, sched[5:].split("/"))
        queries = queries[part::parts]
        warm_up(job)
        plan = plan_localization(job, queries, Path(out), workers=1, order=order)
        t = time.perf_counter()
        records = run_sync(plan)
        print(json.dumps({"elapsed": time.perf_counter() - t, "queries": len(records)}), flush=True)
        return
    from distributed import Client
    with Client(scheduler_file=sched, timeout=60) as client:
        workers = len(client.scheduler_info()["workers"])
        if warm == "1":  # P3 times steady state: each worker loads the network and opens the store first
            client.run(warm_up, job)
        plan = plan_localization(job, queries, Path(out), workers=workers, order=order)
        print(json.dumps({"start": {"shards": len(plan.shards), "pending": len(plan.pending()),
                                    "shard_size": plan.shard_size, "workers": workers}}), flush=True)
        t = time.perf_counter()
        records = run_dask(plan, client)
        print(json.dumps({"elapsed": time.perf_counter() - t, "queries": len(records)}), flush=True)


def read(store: str, conf: str, queries: str, seed: str) -> None:
    from pipeline.mapping.features import FeatureConfig
    from pipeline.store.reader import MapReader
    settings = json.loads(conf)
    settings["image_scales"] = tuple(settings["image_scales"])
    before = rss()
    t0 = time.perf_counter()
    reader = MapReader(store, FeatureConfig.from_dict(settings), cache_images=64)
    open_s = time.perf_counter() - t0
    opened = rss()
    rng = np.random.default_rng(int(seed))
    latencies = []
    obs = None
    for _ in range(int(queries)):
        i = int(rng.integers(0, len(reader.names) - 3))
        t = time.perf_counter()
        obs = reader.observations([i, i + 1, i + 2], 1)
        for k in range(len(settings["image_scales"])):
            reader.features(obs, k)
        latencies.append(time.perf_counter() - t)
    print(json.dumps({"open_s": open_s, "rss_before": before, "rss_open": opened, "rss_end": rss(),
                      "peak_rss": peak_rss(), "read_ms_median": 1e3 * float(np.median(latencies)),
                      "read_ms_p90": 1e3 * float(np.quantile(latencies, 0.9)),
                      "obs_per_query": int(len(obs.rows)) if obs is not None else 0,
                      "bytes_read": reader.stats["bytes"], "blocks": reader.stats["blocks"]}))


def localize(root: str, store: str, out: str, points_per_cell: str = "0", prior: str = Top1.name,
             num_iters: str = "30") -> None:
    from pipeline.evaluate import evaluate, record_errors
    from pipeline.data.synthetic import read_synthetic
    from workflows.localize import plan_localization, run_sync
    _, queries = read_synthetic(root)
    plan = plan_localization(_job(store, float(points_per_cell), prior, int(num_iters)), queries, Path(out),
                             shard_size=8, overwrite=True)
    t = time.perf_counter()
    records = run_sync(plan)
    elapsed = time.perf_counter() - t
    gt = {q.name: q.cam_from_world_gt for q in queries}
    s = evaluate(records, gt, CITY_THRESHOLDS)["all"]["refined"]
    accepted = [r for r in records if r["success"]]
    errors = [record_errors(r, gt[r["name"]])["refined"] for r in accepted]
    (max_t, max_R), _ = CITY_THRESHOLDS
    io = [r["store_io"] for r in records if r.get("store_io")]
    print(json.dumps({"queries": len(records), "s_per_query": elapsed / len(records),
                      "points": float(np.mean([r["num_points"] for r in records])),
                      "iterations": float(np.mean([r["iterations"] for r in records])),
                      "peak_rss": peak_rss(),
                      "recall": {k: v for k, v in s.items() if k.startswith("recall@")},
                      # poses reported as successes, and those of them beyond the first threshold: wrong ones accepted
                      "accepted": len(accepted),
                      "accepted_beyond": sum(not (t <= max_t and R <= max_R) for t, R in errors),
                      "bytes_per_query": sum(x["bytes_read"] / x["shard_queries"] for x in io) / max(len(io), 1)}))


DRIVERS: Dict[str, Callable[..., None]] = {"city": city, "read": read, "localize": localize}


def command(name: str, *args) -> List[str]:
    """The command line that runs driver ``name`` in a new Python process."""
    return [sys.executable, "-m", "workflows.benchmarks.drivers", name, *map(str, args)]


if __name__ == "__main__":
    DRIVERS[sys.argv[1]](*sys.argv[2:])
