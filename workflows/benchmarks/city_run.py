"""Scale benchmarks S1 and P3 (issue 12): a generated city built and localized end to end on a
real Dask cluster (a scheduler and worker processes started with the ``dask`` command).

S1: the 10x10 city (2,400 references) and 5,000 queries (1,250 per condition, all over the
city). Stages timed one by one: rendering, the RGB-D scene, the store (features on 2 workers),
localization on 2 workers. The localization is interrupted twice on purpose: one worker is
killed (SIGKILL) once a quarter of the shards are done, and a replacement worker joins; at
55 % the whole run dies (the localizing process, the scheduler and the workers, SIGKILL). A new
cluster and a new process then resume it. Checked: every query is in ``records.jsonl`` exactly
once, no shard file written before the crash was written again, and the resume ran only the
shards that were missing.

P3: the same first ``--p3-queries`` queries localized afresh on a cluster of 1 worker, then of
2 (one thread each, as every task of the graphs uses), list order; then on 2 workers in region
order, for its effect on the block cache and the bytes read. Workers load the network and open
the store before the clock starts (steady state). Then the machine's own bound, without Dask:
the queries in 1, then split between 2 independent in-process runs at once.
"""

import json
import signal
import subprocess
import time
from pathlib import Path
from typing import Dict, List, Optional

from pipeline.runtime import subprocess_environment
from pipeline.descriptors import Grid

from ..process_cluster import ProcessCluster, wait_for
from .drivers import CITY_THRESHOLDS, command

def driver(root: Path, store: Path, out: Path, cluster: ProcessCluster, limit: int = 0, order: str = "list",
           warm: bool = False):
    return subprocess.Popen(command("city", root, store, out, cluster.sched, limit, order, int(warm)),
                            env=subprocess_environment(OMP_NUM_THREADS="1"),
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)


def lines(proc) -> List[Dict]:
    out, _ = proc.communicate()
    if proc.returncode:
        raise RuntimeError(f"benchmark: the localization process failed with exit code {proc.returncode}")
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def shard_files(out: Path) -> Dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in (out / "shards").glob("shard-*.jsonl")}


def build_city(args, blocks: int, per_condition: int) -> Dict:
    """Render the city (cached), make its RGB-D scene, and build its store on a 2-worker cluster."""
    from pipeline.data.city import CityConfig, generate_city
    from pipeline.mapping.depth import rgbd_scene
    from pipeline.mapping.features import FeatureConfig
    from pipeline.data.synthetic import read_synthetic
    from ..build_map import plan_build, run_dask as build_dask
    root, store = args.work / f"s1-city-{blocks}x{blocks}", args.work / f"s1-city-{blocks}x{blocks}.zarr"
    t0 = time.perf_counter()
    generate_city(root, CityConfig(seed=args.seed, blocks=(blocks, blocks)), queries_per_condition=per_condition,
                  query_spread=0.5)
    mapping, queries = read_synthetic(root)
    t1 = time.perf_counter()
    scene = rgbd_scene(mapping, method="frames", stride=8, min_track_length=3)
    t2 = time.perf_counter()
    conf = FeatureConfig(resize=160, image_scales=(1,), dtype="int8", descriptor=Grid.name, pca=0)
    plan = plan_build(scene, store, conf, batch_size=4)
    cluster = ProcessCluster(args.work, ("w0", "w1"))
    try:
        with cluster.client() as client:
            results = build_dask(plan, client)
    finally:
        cluster.close()
    t3 = time.perf_counter()
    return {"root": root, "store": store, "images": len(mapping), "queries": len(queries),
            "points": len(scene.points), "observations": len(scene.obs_point), "render_s": t1 - t0,
            "scene_s": t2 - t1, "build_s": t3 - t2, "extracted": len(results)}


def s1(args) -> Dict:
    city = build_city(args, args.s1_blocks, args.s1_queries // 4)
    out = args.work / "s1-run"
    if out.exists():
        import shutil
        shutil.rmtree(out)
    # leg 1: 2 workers; a worker killed at 25 % of the shards (a new one joins), everything killed at 55 %
    cluster = ProcessCluster(args.work, ("w0", "w1"))
    t0 = time.perf_counter()
    proc = driver(city["root"], city["store"], out, cluster)
    start = json.loads(proc.stdout.readline())["start"]
    total = start["shards"]
    wait_for(lambda: len(shard_files(out)) >= 0.25 * total, 24 * 3600, 1.0)
    at_worker_kill = len(shard_files(out))
    cluster.kill("w0")
    cluster.add_worker("w2")
    wait_for(lambda: len(shard_files(out)) >= 0.55 * total, 24 * 3600, 1.0)
    proc.send_signal(signal.SIGKILL)
    cluster.close()
    proc.wait()
    leg1_s = time.perf_counter() - t0
    before = shard_files(out)
    # leg 2: a new cluster and process resume
    cluster = ProcessCluster(args.work, ("w0", "w1"))
    try:
        t1 = time.perf_counter()
        msgs = lines(driver(city["root"], city["store"], out, cluster))
        leg2_s = time.perf_counter() - t1
    finally:
        cluster.close()
    resume = msgs[0]["start"]
    after = shard_files(out)
    records = [json.loads(line) for line in (out / "records.jsonl").read_text().splitlines()]
    from pipeline.data.synthetic import read_synthetic
    _, queries = read_synthetic(city["root"])
    names = sorted(q.name for q in queries)
    rewritten = [k for k, t in before.items() if after.get(k) != t]
    return {**city, "shards": total, "shard_size": start["shard_size"], "at_worker_kill": at_worker_kill,
            "at_crash": len(before), "resume_pending": resume["pending"], "leg1_s": leg1_s, "leg2_s": leg2_s,
            "records": len(records), "exactly_once": sorted(r["name"] for r in records) == names,
            "rewritten": len(rewritten), "shards_after": len(after),
            "success": sum(bool(r.get("success")) for r in records),
            "mib_per_query": reads(records)["bytes_per_query"] / 2**20, "recall": recall(records, queries)}


def reads(records: List[Dict]) -> Dict:
    """Store bytes read per query and the block-cache hit rate, as ``pixloc localize`` reports them."""
    from workflows.cli_localize import store_io
    return store_io(records) or {"bytes_per_query": 0.0, "blocks": 0, "hit_rate": 0.0}


def recall(records: List[Dict], queries) -> Dict:
    from pipeline.evaluate import evaluate
    s = evaluate(records, {q.name: q.cam_from_world_gt for q in queries}, CITY_THRESHOLDS)["all"]
    return {k: v for k, v in s["refined"].items() if k.startswith("recall@")}


def timed_run(args, root: Path, store: Path, workers: int, order: str) -> Dict:
    out = args.work / f"p3-{workers}w-{order}"
    if out.exists():
        import shutil
        shutil.rmtree(out)
    cluster = ProcessCluster(args.work, [f"w{k}" for k in range(workers)])
    try:
        msgs = lines(driver(root, store, out, cluster, args.p3_queries, order, warm=True))
    finally:
        cluster.close()
    records = [json.loads(line) for line in (out / "records.jsonl").read_text().splitlines()]
    io = reads(records)
    return {"workers": workers, "order": order, "queries": len(records), "elapsed": msgs[-1]["elapsed"],
            "queries_per_s": len(records) / msgs[-1]["elapsed"], "mib_per_query": io["bytes_per_query"] / 2**20,
            "hit_rate": io["hit_rate"]}


def bare_run(args, root: Path, store: Path, parts: int) -> Dict:
    """The machine's own bound: the queries split between ``parts`` independent processes, each
    localizing its slice in-process (no Dask, one thread, warmed up), all at once; wall time of all."""
    import shutil
    outs = [args.work / f"p3-bare-{parts}-{k}" for k in range(parts)]
    for out in outs:
        shutil.rmtree(out, ignore_errors=True)
    procs = [subprocess.Popen(command("city", root, store, out, f"sync:{k}/{parts}", args.p3_queries, "list", 1),
                              env=subprocess_environment(OMP_NUM_THREADS="1"),
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
             for k, out in enumerate(outs)]
    done = [lines(p)[-1] for p in procs]
    n = sum(d["queries"] for d in done)
    elapsed = max(d["elapsed"] for d in done)
    return {"workers": parts, "order": "bare processes", "queries": n, "elapsed": elapsed,
            "queries_per_s": n / elapsed, "mib_per_query": None, "hit_rate": None}


def p3(args, city: Optional[Dict] = None) -> List[Dict]:
    if city is None:
        city = build_city(args, args.s1_blocks, args.s1_queries // 4)
    rows = [timed_run(args, city["root"], city["store"], w, o) for w, o in ((1, "list"), (2, "list"), (2, "region"))]
    return rows + [bare_run(args, city["root"], city["store"], k) for k in (1, 2)]


def report(args) -> None:
    city = None
    if "S1" in args.parts:
        r = city = s1(args)
        rec = list(r["recall"].values())
        n = r["queries"]
        print(f"\n| S1: city {args.s1_blocks}x{args.s1_blocks} | figure |\n| --- | --- |\n"
              f"| references / map points / observations | {r['images']} / {r['points']} / {r['observations']} |\n"
              f"| queries | {n} (shards of {r['shard_size']}: {r['shards']}) |\n"
              f"| render (references and queries, 160 x 120) | {r['render_s']:.0f} s |\n"
              f"| RGB-D scene (frames, stride 8) | {r['scene_s']:.0f} s |\n"
              f"| store: structure + features, 2 workers | {r['build_s']:.0f} s, "
              f"{r['images'] / r['build_s']:.2f} images/s |\n"
              f"| localize, leg 1 (2 workers; worker killed at {r['at_worker_kill']} shards, everything "
              f"killed at {r['at_crash']}) | {r['leg1_s']:.0f} s |\n"
              f"| localize, leg 2 (new cluster and process: {r['resume_pending']} shards pending) | "
              f"{r['leg2_s']:.0f} s |\n"
              f"| localize in all | {r['leg1_s'] + r['leg2_s']:.0f} s, "
              f"{n / (r['leg1_s'] + r['leg2_s']):.2f} queries/s |\n"
              f"| every query exactly once in records.jsonl | {r['exactly_once']} ({r['records']} records) |\n"
              f"| shard files written before the crash and written again | {r['rewritten']} of {r['at_crash']} |\n"
              f"| resume ran only the missing shards | {r['resume_pending'] == r['shards'] - r['at_crash']} "
              f"({r['resume_pending']} = {r['shards']} - {r['at_crash']}) |\n"
              f"| store MiB read per query | {r['mib_per_query']:.2f} |\n"
              f"| refined and verified | {r['success']} of {n} |\n"
              f"| recall (25 cm, 2 deg) / (1 m, 5 deg) | {100 * (rec[0] or 0):.1f} % / {100 * (rec[1] or 0):.1f} % |")
    if "P3" in args.parts:
        rows = p3(args, city)
        base = rows[0]["queries_per_s"]
        print(f"\n| P3: {rows[0]['queries']} queries | workers | order | s | queries/s | x 1 worker | "
              "store MiB read / query | block-cache hit rate |\n"
              "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |")
        bare = next(r["queries_per_s"] for r in rows if r["order"] == "bare processes")
        for r in rows:
            ratio = r["queries_per_s"] / (bare if r["order"] == "bare processes" else base)
            io = ("- | -" if r["mib_per_query"] is None else
                  f"{r['mib_per_query']:.2f} | {100 * r['hit_rate']:.0f} %")
            print(f"| | {r['workers']} | {r['order']} | {r['elapsed']:.0f} | {r['queries_per_s']:.2f} | "
                  f"{ratio:.2f} | {io} |")
        print("goal: 2 workers >= 1.8 x 1 worker. 'bare processes': the same queries split between independent "
              "in-process runs, x 1 such process: what this machine allows without Dask")
