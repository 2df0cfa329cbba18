"""Benchmark: a query's reads of a map store in an S3 bucket, at added round-trip latencies.

The map (Strecha Herz-Jesus-P8 with 0003.jpg held out, built once into ``--work`` and uploaded) is
served by moto's S3 server on 127.0.0.1 (``workflows.s3_server``) through a proxy that holds every
request ``L`` ms: one round trip of that latency per request. Each map image is taken as a query in
turn; its references are its ``--references`` nearest map images by global descriptor (what
retrieval gives), and its reads are what its refinement reads of the store: the references' point
rows, then their feature blocks at every image scale, cold (the reader's caches cleared first).

Printed per latency: requests (GET, HEAD) and bytes per query and its wall time (median), for the
reader as it is (concurrent reads) against one read at a time (``read_threads=1``, the reader
before), and their ratio; the store's open is timed apart (once per worker process). Goal: a
query's reads under 0.5 s at 50 ms.
"""

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List

import numpy as np

from pipeline.runtime import shared_folder

GOAL_S = 0.5
URL = "s3://maps/hj.zarr"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--work", type=Path, default=Path("outputs/benchmark-store-latency"),
                        help="where the map is built once (reused)")
    parser.add_argument("--latency-ms", type=float, nargs="+", default=[0, 20, 50],
                        help="added latency per request, milliseconds")
    parser.add_argument("--references", type=int, default=5, help="references per query (the localizer's num_dbs)")
    parser.add_argument("--shared", type=Path, default=shared_folder(),
                        help="the shared data folder (default: $PIXLOC_SHARED, else ../shared)")


def build_store(shared: Path, work: Path) -> Path:
    """The benchmark's map, built once with the default features (the README's held-out example)."""
    store = work / "hj.zarr"
    if not store.exists():
        rc = subprocess.run([sys.executable, "-m", "workflows.cli", "build-map", "strecha",
                             str(shared / "data" / "strecha" / "Herz-Jesus-P8"), "--hold-out", "0003.jpg", "--store",
                             str(store), "--sync"]).returncode
        if rc:
            raise SystemExit(f"building the benchmark's map failed (rc {rc})")
    return store


def query_reads(reader, dbs: List[int], proxy) -> Dict:
    """One query's cold reads: its references' point rows and feature blocks at every scale."""
    reader.clear_cache()
    proxy.reset()
    t0 = time.perf_counter()
    obs = reader.observations(dbs, 1)
    for scale in range(len(reader.conf.image_scales)):
        reader.features(obs, scale)
    return {"s": time.perf_counter() - t0, "GET": proxy.requests.get("GET", 0),
            "HEAD": proxy.requests.get("HEAD", 0), "bytes": proxy.bytes_back}


def main(args: argparse.Namespace) -> int:
    import dataclasses

    from pipeline import runtime
    from pipeline.store.reader import MapReader
    from pipeline.store.info import feature_config as store_feature_config
    from workflows.s3_server import CREDENTIALS, DelayingProxy, ServerUnavailable, moto_server
    if not (args.shared / "data" / "strecha").is_dir():
        raise SystemExit(f"{args.shared}/data/strecha not found: give --shared (or set PIXLOC_SHARED)")
    store = build_store(args.shared, args.work)
    conf = store_feature_config(store)
    runtime.set_environment(**CREDENTIALS)
    rows = []
    try:
        with moto_server() as endpoint:
            import s3fs
            s3fs.S3FileSystem(endpoint_url=endpoint).put(str(store), URL[len("s3://"):], recursive=True)
            for latency in args.latency_ms:
                proxy = DelayingProxy(int(endpoint.rsplit(":", 1)[1]), latency / 1000)
                runtime.install(dataclasses.replace(runtime.current(),
                                                    storage_options=json.dumps({"endpoint_url": proxy.endpoint})))
                for threads in (16, 1):
                    proxy.reset()
                    t0 = time.perf_counter()
                    reader = MapReader(URL, conf, read_threads=threads)
                    opened = {"s": time.perf_counter() - t0, **proxy.requests}
                    g = reader.global_descriptors
                    runs = []
                    for q in range(len(reader.names)):
                        similar = [int(i) for i in np.argsort(-(g @ g[q])) if i != q]
                        runs.append(query_reads(reader, similar[:args.references], proxy))
                    rows.append({"latency": latency, "threads": threads, "open": opened, "queries": len(runs),
                                 "s": statistics.median(r["s"] for r in runs),
                                 "GET": np.mean([r["GET"] for r in runs]), "HEAD": np.mean([r["HEAD"] for r in runs]),
                                 "MiB": np.mean([r["bytes"] for r in runs]) / 2**20})
                proxy.close()
    except ServerUnavailable as e:
        raise SystemExit(f"no S3 server: {e}") from None
    print(table(rows, args.references))
    return 0


def table(rows: List[Dict], references: int) -> str:
    lines = [f"a query's store reads ({references} references, every image scale, cold caches), the map in an S3 "
             "bucket (moto on 127.0.0.1) behind a proxy adding the latency to every request:", "",
             "| added latency | reads | requests / query (GET + HEAD) | MiB / query | s / query (median) | "
             "vs one at a time | opening the store |",
             "| ---: | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        base = next(b for b in rows if b["latency"] == r["latency"] and b["threads"] == 1)
        reads = "concurrent (16 threads)" if r["threads"] > 1 else "one at a time"
        goal = " (goal < 0.5 s)" if r["threads"] > 1 and r["latency"] >= 50 else ""
        lines.append(f"| {r['latency']:.0f} ms | {reads} | {r['GET']:.0f} + {r['HEAD']:.0f} | {r['MiB']:.2f} | "
                     f"{r['s']:.3f}{goal} | {base['s'] / r['s']:.1f}x | {r['open']['s']:.2f} s, "
                     f"{r['open'].get('GET', 0) + r['open'].get('HEAD', 0)} requests |")
    fast = [r for r in rows if r["threads"] > 1 and r["latency"] >= 50]
    if fast:
        met = all(r["s"] < GOAL_S for r in fast)
        figures = ", ".join(f"{r['s']:.3f} s at {r['latency']:.0f} ms" for r in fast)
        lines += ["", f"goal: a query's reads under {GOAL_S} s at 50 ms: {'met' if met else 'NOT met'} ({figures})"]
    return "\n".join(lines)
