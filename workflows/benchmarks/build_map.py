"""Benchmark: map building throughput (images/s into the store) and store size, 1 vs 2 workers.

The Maupertuis COLMAP model from the shared data, its 4 images repeated to
make a larger map, built from scratch on a LocalCluster of 1 and then 2
worker processes (one thread each) in one run.
"""

import argparse
import resource
import shutil
import tempfile
import time
from pathlib import Path

from pipeline.mapping.features import FeatureConfig
from pipeline.runtime import shared_folder
from pipeline.mapping.readers.colmap import read_colmap

from .. import executor
from ..build_map import plan_build, run_dask


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shared", type=Path, default=shared_folder(),
                   help="the shared data folder (default: $PIXLOC_SHARED, else ../shared)")
    p.add_argument("--repeat", type=int, default=6, help="copies of the 4 Maupertuis images")
    p.add_argument("--resize", type=int, default=1024, help="longer image side of the features")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to compare")


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main(args: argparse.Namespace) -> int:

    root = args.shared / "data" / "maupertuis"
    scene = read_colmap(root / "reconstruction", root / "images").repeated(args.repeat)
    conf = FeatureConfig(resize=args.resize, image_scales=(4, 1), dtype="float16")
    n_img, n_obs = len(scene.images), len(scene.obs_point)
    print(f"Map building: {n_img} images ({n_obs} observations), features {conf.to_dict()}")
    print(f"{'workers':>7} {'seconds':>8} {'images/s':>9} {'vs 1 worker':>12} "
          f"{'bytes/obs':>10} {'peak MiB/worker':>16}")
    base = None
    for workers in args.workers:
        tmp = Path(tempfile.mkdtemp())
        try:
            store = tmp / "map.zarr"
            with executor.dask_client(workers=workers, dashboard=False) as client:
                client.run(lambda: __import__("pipeline.models").models.network(conf.model))  # warm-up
                plan = plan_build(scene, store, conf)
                t0 = time.perf_counter()
                results = run_dask(plan, client)
                seconds = time.perf_counter() - t0
                peak = max(client.run(_peak_rss_mib).values())
            assert sum(r.status == "done" for r in results) == n_img
            rate = n_img / seconds
            base = base or rate
            print(f"{workers:>7} {seconds:>8.1f} {rate:>9.2f} {rate / base:>11.2f}x "
                  f"{_size(store) / n_obs:>10.0f} {peak:>16.0f}")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0
