"""``pixloc build-map``: build a map store from a COLMAP model, images, known poses or RGB-D frames."""

import argparse
import dataclasses
import logging
import time
from collections import Counter
from pathlib import Path

from pipeline.descriptors import DESCRIPTORS
from pipeline.mapping.features import DTYPES, FeatureConfig
from pipeline.mapping.image_pairs import METHODS as PAIR_METHODS, PairsConfig
from pipeline.mapping.readers.colmap import MAPPERS
from pipeline.mapping.readers.sources import SOURCES, MapSource, describe_source, load_scene, map_kinds
from pipeline.store import location
from pipeline.store.layout import AnotherMap

from . import executor, presets
from .build_map import plan_build, prepare_structure, run_dask, run_sync
from .locks import store_lock, work_dir_lock
from .options import Flag, add_flags, build, given

logger = logging.getLogger(__name__)

# the feature options: the FeatureConfig field each sets (type, choices and default from there:
# ``workflows.options``), overriding a preset's ``features``
FLAGS = {
    "--model": Flag("model", "feature network name or model file"),
    "--resize": Flag("resize", "longer image side at image scale 1"),
    "--image-scales": Flag("image_scales", "image scales, coarse first"),
    "--pad": Flag("pad", "interpolation margin in feature pixels"),
    "--descriptor": Flag("descriptor", "global descriptor for retrieval: " + "; ".join(
        f"{name}: {entry.help}" for name, entry in DESCRIPTORS.items()), tuple(DESCRIPTORS)),
    "--dtype": Flag("dtype", "feature storage: int8 (codes and a scale per row and level; with --pca 48, the compact "
                    "store), float16 (every channel: --dtype float16 alone) or float32", tuple(DTYPES)),
    "--pca": Flag("pca", "store the levels with more than D channels as their D principal components (a PCA of the "
                  "map's features, fitted on 8 of its images; 48 with int8 and two image scales: 257 to 283 bytes per "
                  "observation on the shared scenes); 0: every channel; default 48 with int8, else 0", metavar="D"),
    "--sift": Flag("sift", "also store a SIFT descriptor per observation, extracted at a longer side of N pixels "
                   "(e.g. 1600), for --prior sift: 128 bytes per observation; 0: none", metavar="N"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("kind", choices=map_kinds(), help="what the map is built from")
    p.add_argument("path", type=Path, help="; ".join(f"{kind}: {SOURCES[kind].help}" for kind in map_kinds()))
    p.add_argument("--store", required=True, help="output map store: a .zarr folder, or a URL (s3://bucket/map.zarr; "
                   "docs/cluster.md)")
    p.add_argument("--images", type=Path, help="image folder of a COLMAP model (default: PATH/../images), a Bundler "
                   "bundle or an OpenSfM reconstruction")
    p.add_argument("--sequences", type=int, nargs="+", default=[], help="7-Scenes sequences of the map")
    p.add_argument("--rgbd-points", choices=["tsdf", "frames"], default="tsdf",
                   help="RGB-D sources: map points from a TSDF fusion of the depth maps, or from each frame's depth")
    p.add_argument("--densify", action="store_true", help="move SfM points onto the depth maps")
    p.add_argument("--hold-out", nargs="+", default=[], metavar="NAME",
                   help="images to leave out of the map, e.g. the queries of a held-out split (SfM and "
                        "triangulation never see them)")
    p.add_argument("--intrinsics", type=float, nargs=4, default=[], metavar=("FX", "FY", "CX", "CY"),
                   help="posetxt: pinhole intrinsics of colour and depth (COLMAP convention)")
    p.add_argument("--depth-scale", type=float, default=1e-3, help="posetxt: depth units to scene units")
    p.add_argument("--depth-ext", default=".png", help="posetxt: depth file extension")
    add_flags(p, FeatureConfig, FLAGS)
    p.add_argument("--chunk-rows", type=int, default=256, help="rows per chunk (the unit of a partial read)")
    p.add_argument("--shard-rows", type=int,
                   help="rows per shard file (a multiple of --chunk-rows; default: fits 90%% of the images)")
    p.add_argument("--pairs", choices=list(PAIR_METHODS), default="auto",
                   help="image pairs matched for sfm, strecha and kapture sources: auto (exhaustive below "
                        f"{PairsConfig().exhaustive_below} images, then spatial for known poses and retrieval "
                        "otherwise), exhaustive, spatial, sequential, retrieval or file")
    p.add_argument("--pairs-file", type=Path, help="an hloc pairs file (name0 name1 per line): --pairs file")
    p.add_argument("--pairs-neighbors", type=int, default=PairsConfig().num_neighbors,
                   help="spatial/retrieval: neighbours per image")
    p.add_argument("--mapper", choices=list(MAPPERS), default="incremental",
                   help="sfm sources: incremental (COLMAP's), global (GLOMAP's rotation averaging and global "
                        "positioning; focal lengths calibrated from the view graph where no image has one) or "
                        "hierarchical (incremental per cluster of images, merged); docs/benchmarks.md, Mapping")
    p.add_argument("--batch-size", type=int, default=1, help="images per task")
    p.add_argument("--device", default="cpu", help="torch device of the feature network (cpu, cuda, cuda:1)")
    p.add_argument("--work-dir", type=Path, help="SfM/triangulation files and the log (default: the store's path "
                   "with .work for its suffix: map.work for map.zarr; for a URL, NAME.work in the current folder)")
    p.add_argument("--scheduler", help="an existing Dask scheduler: its address (tcp://host:8786) or the file "
                   "that 'dask scheduler "
                   "--scheduler-file' wrote (default: a local cluster; docs/cluster.md)")
    p.add_argument("--workers", type=int, default=2, help="worker processes of the local cluster")
    p.add_argument("--sync", action="store_true", help="run in this process, without Dask")
    p.add_argument("--overwrite", action="store_true", help="rebuild a store that holds another map or features")
    p.add_argument("--dry-run", action="store_true", help="print the plan and exit")
    p.add_argument("--preset", help="dataset preset with the paper's settings: " + ", ".join(presets.available()))
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from .cli_localize import absolute
    conf = build(FeatureConfig, presets.feature_settings(presets.load(args.preset) if args.preset else None),
                 given(args, FLAGS), where="build-map options")
    if Path(conf.model).suffix:  # a model file, recorded absolute
        conf = dataclasses.replace(conf, model=str(absolute(conf.model)))
    from pixloc.nets.registry import model_recipe
    model_recipe(conf.model)  # an unknown model or a bad file is refused now, not after the SfM or triangulation
    store = location.normalize(args.store)
    if not location.is_url(store) and Path(store).is_file():
        raise ValueError(f"--store {store} is a file: a map store is a folder (or a URL).")
    if location.exists(store) and not args.overwrite:
        from pipeline.store.info import check_store
        check_store(store)  # something else than a store there is refused now, not after the reconstruction
    source = MapSource(args.kind, absolute(args.path), absolute(args.images), tuple(args.sequences),
                       args.rgbd_points, args.densify, tuple(args.intrinsics), args.depth_scale, args.depth_ext,
                       tuple(args.hold_out), args.mapper)
    if args.mapper != MapSource.mapper and "mapper" not in source.format.reads:  # not ignored without a word
        how = "triangulated from its known poses" if source.format.reconstructs else "read as it is"
        raise ValueError(f"--mapper {args.mapper}: only an sfm source is reconstructed by SfM; a {args.kind} source "
                         f"is {how}.")
    pairs = PairsConfig("file" if args.pairs_file and args.pairs == "auto" else args.pairs,
                        args.pairs_neighbors, path=str(absolute(args.pairs_file)) if args.pairs_file else None)
    work_dir = absolute(args.work_dir) or location.work_dir(store)
    t0 = time.time()
    if args.dry_run and source.format.reconstructs:  # a dry run computes and writes nothing
        print(f"map store      {store}" + (" (overwritten)" if args.overwrite else "") + f"\nsource         "
              f"{describe_source(source.to_dict())}\nfeatures       {conf.to_dict()} on {args.device}\nstages:\n"
              f"  0 reconstruction  {source.format.reconstructs} of the images in {source.path}, in {work_dir} "
              "(reused there when it finished with the same images and settings)\n"
              "  1 structure, 2 features: counted once the reconstruction exists\n(dry run: nothing computed or "
              "written)")
        return 0
    session = executor.Session(sync=args.sync, scheduler=args.scheduler, workers=args.workers, device=args.device)
    with store_lock(store, work_dir), work_dir_lock(work_dir), session:
        from .logs import colmap_to_file, to_file
        log = to_file(work_dir / "build-map.log")
        colmap_to_file(work_dir)
        print(f"log            {log} (COLMAP's in {work_dir}/colmap.INFO.*)")
        from pipeline.mapping.structure import Tasks, in_process
        from pipeline.progress import Progress
        # SIFT and matching in shards on the session's workers (one pycolmap thread each), or here on every core:
        # with --sync, and for a store in a bucket, whose workers may share no folder with this process
        here = args.sync or location.is_url(store)
        tasks = Tasks(run=in_process if here else session.run, threads=0 if here else 1, progress=Progress)
        scene = load_scene(source, work_dir, pairs, tasks=tasks)
        if tasks.seconds:
            logger.info("structure stage: %s", ", ".join(f"{k} {v:.1f} s" for k, v in tasks.seconds.items()))
        try:
            plan = plan_build(scene, store, conf, batch_size=args.batch_size, device=args.device,
                              chunk_rows=args.chunk_rows, shard_rows=args.shard_rows, source=source.to_dict(),
                              overwrite=args.overwrite)
            print(plan.describe())
            if args.dry_run:
                return 0
            if not plan.overwrite and location.exists(store) and not prepare_structure(plan):
                # cheap; re-admits refused images whose problem is gone
                print(f"\nAll {len(scene.images)} images of {store} already have features (or were refused): "
                      "nothing to do (--overwrite rebuilds it).")
                return 0
        except AnotherMap as e:
            if not source.format.reconstructs:
                raise
            raise AnotherMap(f"{e} The {source.kind} source's map comes from {source.format.reconstructs}, which "
                             f"gives another map each time it runs: a rerun reuses the one finished in its work "
                             f"folder, here {work_dir}. If that is not the folder that built this store, give "
                             "that one with --work-dir (a store copied or moved without its work folder cannot "
                             "be resumed or repaired: rebuild it with --overwrite).") from None
        results = session.run_plan(plan, run_sync, run_dask)
    counts = Counter(r.status for r in results)
    already = len(scene.images) - sum(len(b) for b in plan.batches) + counts.get("skipped", 0)
    print(f"\n{counts.get('done', 0)} images extracted, {already} already done or refused, "
          f"{counts.get('failed', 0)} failed, in {time.time() - t0:.1f} s -> {args.store}")
    for r in results:
        if r.status == "failed":
            print(f"  failed: {r.name}: {r.reason}")
    for name, reason in list(plan.refused.items())[:20]:
        print(f"  refused: {name}: {reason}")
    if len(plan.refused) > 20:
        print(f"  ... and {len(plan.refused) - 20} more refused (the store's failed images: pixloc check-store)")
    return 0


def add_check_store_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("store", help="a map store (a .zarr folder or a URL)")
    p.add_argument("--repair", action="store_true", help="mark the images whose files are damaged or missing "
                   "pending, so that the same build-map command rebuilds only them")
    p.set_defaults(func=check_store_main)


def check_store_main(args: argparse.Namespace) -> int:
    """Verify every chunk (checksums) and the layout; exit 1 when anything is bad."""
    from pipeline.store.check import check_store
    report = check_store(args.store, progress=lambda name: logger.debug("checking %s", name))
    print(report.summary())
    from pipeline.store.info import feature_configs
    from pipeline.store.layout import StoreError
    try:  # what each feature group holds, its global descriptor among it (a store keeps the one it was built by)
        for conf in feature_configs(args.store):
            print(f"  features of {conf.model} at {conf.resize} px, image scales {list(conf.image_scales)}, "
                  f"{conf.dtype}{f' + PCA {conf.pca}' if conf.pca else ''}; global descriptor {conf.descriptor}"
                  f"{f'; SIFT at {conf.sift} px' if conf.sift else ''}")
    except (StoreError, OSError, KeyError, ValueError, TypeError) as e:  # damaged: the summary above names it
        logger.debug("feature groups not listed: %s", e)
    if args.repair and report.bad_images():
        from pipeline.store.check import mark_pending
        n = mark_pending(args.store, report.bad_images())
        print(f"repair: {len(report.bad_images())} images marked pending ({n} feature rows); run the build-map "
              "command again to rebuild them")
    return 0 if report.ok else 1
