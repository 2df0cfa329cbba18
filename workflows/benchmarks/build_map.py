"""Benchmark: map building throughput (images/s into the store) and store size, 1 vs 2 workers,
and with and without SIFT per observation.

The Maupertuis COLMAP model from the shared data, its 4 images repeated to
make a larger map, built from scratch on a LocalCluster of 1 and then 2
worker processes (one thread each) in one run; ``--sift 0 1600`` builds each
with no SIFT and with SIFT extracted at 1,600 px (build-map's default), the
first row (the first worker count, the first SIFT size) being the baseline of the others.
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
    p.add_argument("--sift", type=int, nargs="+", default=[0], metavar="N",
                   help="SIFT per observation at a longer side of N px (0: none) to compare (default 0)")
    p.add_argument("--dtype", default="float16", help="feature storage (build-map's default: int8, compact)")


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main(args: argparse.Namespace) -> int:

    root = args.shared / "data" / "maupertuis"
    scene = read_colmap(root / "reconstruction", root / "images").repeated(args.repeat)
    n_img, n_obs = len(scene.images), len(scene.obs_point)
    features = FeatureConfig(resize=args.resize, image_scales=(4, 1), dtype=args.dtype).to_dict()
    print(f"Map building: {n_img} images ({n_obs} observations), features {features} (sift as the row says)")
    print(f"{'workers':>7} {'sift':>5} {'seconds':>8} {'images/s':>9} {'vs first':>9} "
          f"{'bytes/obs':>10} {'vs first':>9} {'peak MiB/worker':>16}")
    base = None
    for workers, sift in [(w, s) for w in args.workers for s in args.sift]:
        conf = FeatureConfig(resize=args.resize, image_scales=(4, 1), dtype=args.dtype, sift=sift)
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
            rate, size = n_img / seconds, _size(store) / n_obs
            base = base or (rate, size)
            print(f"{workers:>7} {sift:>5} {seconds:>8.1f} {rate:>9.2f} {rate / base[0]:>8.2f}x "
                  f"{size:>10.0f} {size / base[1]:>8.2f}x {peak:>16.0f}")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0
