"""``pixloc build-map``: build a map store from a COLMAP model, images, known poses or RGB-D frames."""

import argparse
import logging
import time
from collections import Counter
from pathlib import Path

from pipeline.features import FeatureConfig

from .build_map import plan_build, run_dask, run_sync
from .sources import KINDS, MapSource, load_scene

logger = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("kind", choices=KINDS, help="what the map is built from")
    p.add_argument("path", type=Path, help="COLMAP model folder, image folder, Strecha/kapture/7-Scenes root")
    p.add_argument("--store", type=Path, required=True, help="output map store (a .zarr folder)")
    p.add_argument("--images", type=Path, help="image folder of a COLMAP model (default: PATH/../images)")
    p.add_argument("--sequences", type=int, nargs="+", default=[], help="7-Scenes sequences of the map")
    p.add_argument("--rgbd-points", choices=["tsdf", "frames"], default="tsdf")
    p.add_argument("--densify", action="store_true", help="move SfM points onto the depth maps")
    p.add_argument("--intrinsics", type=float, nargs=4, default=[], metavar=("FX", "FY", "CX", "CY"),
                   help="posetxt: pinhole intrinsics of colour and depth (COLMAP convention)")
    p.add_argument("--depth-scale", type=float, default=1e-3, help="posetxt: depth units to scene units")
    p.add_argument("--depth-ext", default=".png", help="posetxt: depth file extension")
    p.add_argument("--model", default="lite0-imagenet", help="feature network name or checkpoint path")
    p.add_argument("--resize", type=int, default=1024, help="longer image side at image scale 1")
    p.add_argument("--image-scales", type=int, nargs="+", default=[4, 1])
    p.add_argument("--pad", type=int, default=2, help="interpolation margin in feature pixels")
    p.add_argument("--descriptor", choices=["gem", "grid"], default="gem",
                   help="global descriptor for retrieval (gem pooling, or a 2x3 grid of mean-centred features)")
    p.add_argument("--chunk-rows", type=int, default=256)
    p.add_argument("--batch-size", type=int, default=1, help="images per task")
    p.add_argument("--device", default="cpu")
    p.add_argument("--work-dir", type=Path, help="SfM/triangulation files (default: STORE.work)")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler (default: a local cluster)")
    p.add_argument("--workers", type=int, default=2, help="worker processes of the local cluster")
    p.add_argument("--sync", action="store_true", help="run in this process, without Dask")
    p.add_argument("--dry-run", action="store_true", help="print the plan and exit")
    p.add_argument("--preset", help="dataset preset with the paper's settings (see workflows/presets)")
    p.set_defaults(func=main)
    p.set_defaults(_parser_defaults={a.dest: a.default for a in p._actions})


def main(args: argparse.Namespace) -> int:
    if args.preset:
        from . import presets
        presets.apply(args, presets.load(args.preset), args._parser_defaults)
    source = MapSource(args.kind, args.path, args.images, tuple(args.sequences), args.rgbd_points, args.densify,
                       tuple(args.intrinsics), args.depth_scale, args.depth_ext)
    conf = FeatureConfig(args.model, args.resize, tuple(args.image_scales), args.pad, descriptor=args.descriptor)
    work_dir = args.work_dir or args.store.with_suffix(".work")
    t0 = time.time()
    scene = load_scene(source, work_dir)
    plan = plan_build(scene, args.store, conf, batch_size=args.batch_size, device=args.device,
                      chunk_rows=args.chunk_rows, source=source.to_dict())
    print(plan.describe())
    if args.dry_run:
        return 0
    if args.sync:
        results = run_sync(plan, progress=True)
    else:
        from distributed import Client, LocalCluster
        if args.scheduler:
            client = Client(args.scheduler)
        else:
            resources = {"GPU": 1} if args.device.startswith("cuda") else None
            cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                                   resources=resources, dashboard_address=":0")
            client = Client(cluster)
        print(f"Dask dashboard: {client.dashboard_link}")
        with client:
            results = run_dask(plan, client, progress=True)
    counts = Counter(r.status for r in results)
    already = len(scene.images) - sum(len(b) for b in plan.batches) + counts.get("skipped", 0)
    print(f"\n{counts.get('done', 0)} images extracted, {already} already done or refused, "
          f"{counts.get('failed', 0)} failed, in {time.time() - t0:.1f} s -> {args.store}")
    for r in results:
        if r.status == "failed":
            print(f"  failed: {r.name}: {r.reason}")
    return 0
