"""Benchmarks of scale (docs/scaling.md): ``--parts S3`` (default), ``S2``, ``S4``, ``S5``, and ``S1`` and
``P3`` (``workflows/benchmarks/city_run.py``: a city end to end on a Dask cluster, killed and resumed).

S2: generated cities (``pipeline.data.city.SyntheticCity``) of about 100, 500 and 2,000
reference images (2x2, 4x4, 10x10 blocks), each built into a map (RGB-D frames, int8 features)
and the same number of queries localized in a fresh process per prior (``--city-priors``: the
top-1 reference's pose, and SIFT + PnP refined; retrieval restricted to the query's block side,
as a GPS tag would): seconds per query and the process's peak RSS per map size, which must stay
flat (within 1.2x) and under 2 GB, and recall at (25 cm, 2 deg), at least 70 % and within 5
points across sizes (issue 29).

S3: the map store at the size of Aachen Day-Night v1.1.

S4: triangulation from known poses (SIFT, spatial pairs, pycolmap) of 200 and 2,000 references of
the 10x10 city, rendered at 480 x 360 with fine stains on every surface (the procedural walls
alone repeat too much for SIFT): time against the number of images.

S5: adding 10 % new images (the last tenth of the 4x4 city's references) to a built map of the
other 90 %, against building the whole map from scratch (structure and features, one process).

A store of 6,697 reference images, 6.1 M points and 29.8 M observations (the Aachen v1.1
LoFTR model's counts; ``--fraction`` scales them down), written with the real layout and code
path (``create_store``, ``init_features``, ``write_image_features``: sharding, int8 codes,
checksums). Only the values are synthetic: features are Gaussian noise, which compresses worse
than real features (the worst case for bytes on disk), observation counts per image are
log-normal around the mean, and each image sees points of its own part of the map.

Then, in a fresh process: the time to open a ``MapReader``, its resident memory, and the
latency of the reads of one query (its 3 references' observations and features, cold cache),
over ``--queries`` queries. Figures are printed next to the goals of issue 12 and to the
version-2 layout (one file per 256-row chunk per array, float16), computed for the same counts.
"""

import argparse
import dataclasses
import json
import subprocess
import time
from pathlib import Path
from typing import Dict

import numpy as np

from pipeline.runtime import shared_folder

from pipeline.mapping.features import FeatureConfig, ImageFeatures
from pipeline.scene import CameraRecord, ImageRecord, Scene
from pipeline.descriptors import Grid
from pipeline.localization.priors import Search, Sift, Top1

from .drivers import command

AACHEN = {"images": 6697, "points": 6_100_000, "observations": 29_800_000}
DIMS = [32, 128, 128]
GOALS = {"bytes": 10e9, "files": 150_000, "rss": 2 * 2**30}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--parts", nargs="+", default=["S3"], choices=["S1", "S2", "S3", "S4", "S5", "P3"],
                   help="the parts of the benchmark to run (docs/scaling.md)")
    p.add_argument("--cities", type=int, nargs="+", default=[2, 4, 10],
                   help="S2: blocks per side of each city (96, 384 and 2,400 references)")
    p.add_argument("--city-queries", type=int, default=8, help="S2: queries per condition (4 conditions)")
    p.add_argument("--city-priors", nargs="+", default=[Top1.name, Sift.name],
                   choices=[Top1.name, Search.name, Sift.name],
                   help="S2: the priors each city's queries are localized from, each in a process of its own (top1: "
                   "the retrieved reference's pose; sift: SIFT + PnP refined on the two finest levels)")
    p.add_argument("--city-style", choices=["photos", "procedural"], default="photos",
                   help="S2: photos (default): 320 px, streets 14 m wide, references every 2 m, the Strecha photos "
                   "of --shared on every facade, queries around the references; procedural: the city before "
                   "(160 px, 10 m streets, every 4 m, procedural facades, queries anywhere on the street)")
    p.add_argument("--shared", type=Path, default=shared_folder(),
                   help="the shared data folder, for the photo city's textures (default: $PIXLOC_SHARED, "
                   "else ../shared)")
    p.add_argument("--s1-blocks", type=int, default=10,
                   help="S1, P3: blocks per side of the city (10: 2,400 references)")
    p.add_argument("--s1-queries", type=int, default=5000, help="S1: queries (a quarter per condition)")
    p.add_argument("--p3-queries", type=int, default=480, help="P3: queries localized with 1 and 2 workers")
    p.add_argument("--s4-images", type=int, nargs="+", default=[200, 2000],
                   help="S4: references triangulated, the nearest the city's corner (the city of --s1-blocks)")
    p.add_argument("--s4-neighbors", type=int, default=10, help="S4: spatial pairs per image")
    p.add_argument("--s4-from", choices=["centre", "corner"], default="centre",
                   help="S4: the references triangulated are those nearest the city's centre (default) or corner")
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-scale"),
                   help="work folder (stores, cities, runs)")
    p.add_argument("--fraction", type=float, default=1.0, help="of the Aachen v1.1 counts (default 1: full size)")
    p.add_argument("--dtype", default="int8", choices=["int8", "float16"], help="feature storage of the S3 store")
    p.add_argument("--image-scales", type=int, nargs="+", default=[1],
                   help="image scales stored (default [1]; the Aachen preset's [4, 1] doubles the features)")
    p.add_argument("--pca", type=int, default=0,
                   help="S3: store the 128-channel levels as this many components (random bases; default 0: off)")
    p.add_argument("--queries", type=int, default=50, help="queries whose reads are timed")
    p.add_argument("--seed", type=int, default=0, help="seed of the generated data")
    p.add_argument("--reuse", action="store_true", help="S3: measure the store a previous run wrote (same counts)")


def synthetic_scene(num_images: int, num_points: int, num_obs: int, seed: int = 0) -> Scene:
    """Images along a line of the map, each seeing points of its own stretch of it."""
    rng = np.random.default_rng(seed)
    counts = rng.lognormal(0.0, 0.6, num_images)
    counts = np.maximum(1, np.round(counts / counts.sum() * num_obs)).astype(np.int64)
    counts[np.argmax(counts)] += num_obs - counts.sum()
    camera = CameraRecord("PINHOLE", 1600, 1200, (1200.0, 1200.0, 800.0, 600.0))
    images = [ImageRecord(f"db/{i:05d}.jpg", Path(f"db/{i:05d}.jpg"), camera,
                          np.concatenate([np.eye(3), [[0.0], [0.0], [-0.5 * i]]], 1)) for i in range(num_images)]
    obs_image = np.repeat(np.arange(num_images), counts)
    centre = (obs_image + 0.5) * num_points / num_images
    window = 4 * num_points / num_images
    obs_point = np.clip(centre + rng.uniform(-window, window, len(obs_image)), 0, num_points - 1).astype(np.int64)
    obs_xy = rng.uniform(0, [1600, 1200], (len(obs_image), 2)).astype(np.float32)
    points = rng.normal(size=(num_points, 3))
    return Scene(images, points, obs_point, obs_image, obs_xy)


def build(store: Path, scene: Scene, conf: FeatureConfig, seed: int) -> Dict:
    from pipeline.store.info import observations_per_image
    from pipeline.store.feature_groups import FeatureWriter, finish_group
    from pipeline.store.structure import create_store
    rng = np.random.default_rng(seed + 1)
    t0 = time.perf_counter()
    create_store(store, scene, overwrite=True)
    writer = FeatureWriter(store, conf, "synthetic", DIMS, fit_pca=lambda: {  # random orthonormal bases
        (k, level): (np.zeros(d, np.float32), np.linalg.qr(rng.normal(size=(d, conf.pca)))[0].astype(np.float32))
        for k in range(len(conf.image_scales)) for level, d in enumerate(DIMS) if d > conf.pca})
    t1 = time.perf_counter()
    num_obs = observations_per_image(store)
    for i, n in enumerate(num_obs):
        samples = {(k, level): (rng.normal(size=(n, d)).astype(np.float32), rng.uniform(0, 1, n).astype(np.float32),
                                np.ones(n, bool))
                   for k in range(len(conf.image_scales)) for level, d in enumerate(DIMS)}
        writer.write(i, ImageFeatures(samples, rng.normal(size=DIMS[-1]).astype(np.float32)))
        if i % 500 == 0:
            print(f"  features: {i}/{len(num_obs)} images, {time.perf_counter() - t1:.0f} s", flush=True)
    finish_group(store, conf)  # as a finished build does
    t2 = time.perf_counter()
    return {"structure_s": t1 - t0, "features_s": t2 - t1, "images_per_s": len(num_obs) / (t2 - t1)}


def v2_figures(num_obs: np.ndarray, scales: int) -> Dict:
    """The version-2 layout for the same counts: per image, ceil(n / 256) chunks of each of
    3 arrays per scale and level, and 1,047 bytes per observation with two image scales (measured
    on the demo's float16 store), so half of that per image scale."""
    chunks = np.maximum(1, -(-num_obs // 256))
    return {"files": int(chunks.sum() * 3 * len(DIMS) * scales + 3 * len(num_obs)),
            "bytes": float(num_obs.sum() * 1047 / 2 * scales)}


def city_rows(args) -> list:
    """S2: per map size, the build and the localization of the same number of queries."""
    from pipeline.mapping.depth import rgbd_scene
    from pipeline.data.city import generate_city
    from pipeline.data.synthetic import read_synthetic
    from ..build_map import plan_build, run_sync as build_sync
    rows = []
    style = city_style(args.city_style, args.shared)
    for n in args.cities:
        root = args.work / f"city-{n}x{n}" if args.city_style == "procedural" else args.work / f"photo-city-{n}x{n}"
        t0 = time.perf_counter()
        generate_city(root, dataclasses.replace(style["city"], seed=args.seed, blocks=(n, n)),
                      queries_per_condition=args.city_queries, camera=style["camera"], query_spread=0.5,
                      query_block="0-0", queries_near_references=style["near_references"])
        mapping, _ = read_synthetic(root)
        t1 = time.perf_counter()
        scene = rgbd_scene(mapping, method="frames", stride=8, min_track_length=3)
        store = root.with_suffix(".zarr")
        conf = FeatureConfig(resize=style["camera"].width, image_scales=(1,), dtype="int8", descriptor=Grid.name, pca=0)
        build_sync(plan_build(scene, store, conf))
        t2 = time.perf_counter()
        for prior in args.city_priors:
            run = root.parent / (f"{root.name}-run" + ("" if prior == Top1.name else f"-{prior}"))
            out = subprocess.run(command("localize", root, store, run, style["points_per_cell"], prior),
                                 capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append({**r, "blocks": f"{n}x{n}", "prior": prior, "images": len(mapping),
                         "map_points": len(scene.points), "observations": len(scene.obs_point),
                         "render_s": t1 - t0, "build_s": t2 - t1})
            print(f"  city {n}x{n}, {prior}: {len(mapping)} images, {r['s_per_query']:.2f} s/query, "
                  f"peak RSS {r['peak_rss'] / 2**20:.0f} MiB", flush=True)
    return rows


def city_goals(rows) -> list:
    """S2's goal lines per prior: time and memory against the smallest city, recall's level and spread."""
    lines = []
    for prior in dict.fromkeys(r["prior"] for r in rows):
        mine = [r for r in rows if r["prior"] == prior]
        base = mine[0]
        slow = max(r["s_per_query"] / base["s_per_query"] for r in mine)
        peak = max(r["peak_rss"] for r in mine) / 2**20
        recall = [100 * (list(r["recall"].values())[0] or 0) for r in mine]
        lines.append(f"{prior}: time at most {slow:.2f} x the smallest city's (goal 1.2x): "
                     f"{'met' if slow <= 1.2 else 'not met'}; peak RSS at most {peak:.0f} MiB (goal 2048): "
                     f"{'met' if peak <= 2048 else 'not met'}; recall at (25 cm, 2 deg) {min(recall):.1f} to "
                     f"{max(recall):.1f} % (goal at least 70 % and within 5 points): "
                     f"{'met' if min(recall) >= 70 and max(recall) - min(recall) <= 5 else 'not met'}")
    return lines


def city_style(name: str, shared: Path) -> Dict:
    """S2's city: ``photos``, a city the method can localize (the photos of Strecha's two scenes
    on every facade, 320 px, 14 m streets, references every 2 m, queries around the references),
    or ``procedural``, the city before (160 px, 10 m streets, every 4 m, procedural facades,
    queries anywhere on the street). The photo city's depth-fused map is dense: its queries run
    the LM on one point per feature-map cell at most (``points_per_cell``, as the 7scenes preset)."""
    from pipeline.data.city import CityConfig
    if name == "procedural":
        return {"city": CityConfig(), "camera": CameraRecord("PINHOLE", 160, 120, (125.0, 125.0, 80.0, 60.0)),
                "near_references": False, "points_per_cell": 0}
    photos = tuple(str(p) for p in sorted((shared / "data" / "strecha").glob("*/images/*.jpg")))
    if not photos:
        raise SystemExit(f"pixloc: error: no Strecha photos under {shared / 'data' / 'strecha'} for the photo city: "
                         "give --shared, or --city-style procedural")
    return {"city": CityConfig(street=14.0, spacing=2.0, textures=photos),
            "camera": CameraRecord("PINHOLE", 320, 240, (250.0, 250.0, 160.0, 120.0)), "near_references": True,
            "points_per_cell": 1}


def add_rows(args) -> Dict:
    """S5: time to add the last 10 % of a city's references to a map of the rest, and to build all."""
    import shutil

    from pipeline.mapping.depth import rgbd_scene
    from pipeline.data.city import CityConfig, generate_city
    from pipeline.data.synthetic import read_synthetic
    from ..build_map import plan_build, run_sync as build_sync
    root = args.work / "city-4x4"
    generate_city(root, CityConfig(seed=args.seed, blocks=(4, 4)), queries_per_condition=args.city_queries,
                  query_spread=0.5, query_block="0-0")
    mapping, _ = read_synthetic(root)
    n_new = len(mapping) // 10
    conf = FeatureConfig(resize=160, image_scales=(1,), dtype="int8", descriptor=Grid.name, pca=0)
    t0 = time.perf_counter()
    scene = rgbd_scene(mapping, method="frames", stride=8, min_track_length=3)
    scene_s = time.perf_counter() - t0
    first = rgbd_scene(mapping[:-n_new], method="frames", stride=8, min_track_length=3)
    full, inc = args.work / "s5-full.zarr", args.work / "s5-incremental.zarr"
    for path in (full, inc):
        shutil.rmtree(path, ignore_errors=True)
    t0 = time.perf_counter()
    build_sync(plan_build(scene, full, conf))
    full_s = time.perf_counter() - t0
    build_sync(plan_build(first, inc, conf))
    t0 = time.perf_counter()
    results = build_sync(plan_build(scene, inc, conf))
    add_s = time.perf_counter() - t0
    return {"images": len(mapping), "new": n_new, "extracted": len(results), "scene_s": scene_s,
            "full_s": full_s, "add_s": add_s}


def triangulation_rows(args) -> list:
    """S4: triangulation from the known poses of the ``--s4-images`` references nearest the city's
    centre (nested compact parts of the 10x10 city, rendered at 480 x 360 with fine stains for SIFT;
    ``--s4-from corner``: nearest its corner), each from scratch in its own work folder: SIFT,
    matching of spatial pairs, triangulation, each timed."""
    import shutil

    from pipeline.data.city import CityConfig, generate_city
    from pipeline.mapping.image_pairs import PairsConfig, spatial_pairs
    from pipeline.mapping.readers.colmap import triangulate_known_poses
    from pipeline.regions import camera_centres
    from pipeline.data.synthetic import read_synthetic
    root = args.work / f"s4-city-{args.s1_blocks}x{args.s1_blocks}"
    t0 = time.perf_counter()
    generate_city(root, CityConfig(seed=args.seed, blocks=(args.s1_blocks, args.s1_blocks), detail=0.3),
                  queries_per_condition=0, camera=CameraRecord("PINHOLE", 480, 360, (375.0, 375.0, 240.0, 180.0)))
    mapping, _ = read_synthetic(root)
    print(f"  S4: {len(mapping)} references rendered (or reused) in {time.perf_counter() - t0:.0f} s", flush=True)
    centres = camera_centres(np.stack([im.cam_from_world for im in mapping]))
    origin = np.zeros(2) if args.s4_from == "corner" else centres[:, :2].min(0) / 2 + centres[:, :2].max(0) / 2
    order = np.argsort(np.linalg.norm(centres[:, :2] - origin, axis=1), kind="stable")  # nearest first
    pairs = PairsConfig(method="spatial", num_neighbors=args.s4_neighbors)
    rows = []
    for n in args.s4_images:
        images = [mapping[i] for i in sorted(order[:n])]
        work = args.work / f"s4-triangulation-{n}"
        shutil.rmtree(work, ignore_errors=True)
        t0, stages = time.perf_counter(), {}
        scene = triangulate_known_poses(images, root, work, pairs=pairs, timings=stages)
        elapsed = time.perf_counter() - t0
        matched = len(spatial_pairs([im.name for im in images], [im.cam_from_world for im in images],
                                    pairs.num_neighbors, pairs.max_angle))
        rows.append({"images": n, "pairs": matched, "exhaustive_pairs": n * (n - 1) // 2, "seconds": elapsed,
                     "points": len(scene.points), "observations": len(scene.obs_point), **stages})
        print(f"  S4: {n} images, {matched} pairs, {len(scene.points)} points in {elapsed:.0f} s", flush=True)
    return rows


def main(args: argparse.Namespace) -> int:
    args.work.mkdir(parents=True, exist_ok=True)
    if "S4" in args.parts:
        rows = triangulation_rows(args)
        base = rows[0]
        print(f"\n| S4: triangulation, known poses (references nearest the {args.s4_from}) | images | pairs matched "
              "(spatial) | exhaustive pairs | points | observations | SIFT s | matching s | triangulation s | "
              "seconds | x smallest | images x smallest |")
        print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        for r in rows:
            print(f"| | {r['images']} | {r['pairs']} | {r['exhaustive_pairs']} | {r['points']} | "
                  f"{r['observations']} | {r['sift']:.0f} | {r['matching']:.0f} | {r['triangulation']:.0f} | "
                  f"{r['seconds']:.0f} | {r['seconds'] / base['seconds']:.2f} | {r['images'] / base['images']:.0f} |")
        print("goal: <= 10 x the time of the smallest (exhaustive pairs would be about 100 x)")
    if "S1" in args.parts or "P3" in args.parts:
        from .city_run import report
        report(args)
    if "S5" in args.parts:
        r = add_rows(args)
        print(f"\n| S5: city 4x4 | images | seconds | x full build |\n| --- | ---: | ---: | ---: |\n"
              f"| full build (structure + features) | {r['images']} | {r['full_s']:.1f} | 1.00 |\n"
              f"| add {r['new']} new images to a map of the others ({r['extracted']} extracted) | {r['new']} | "
              f"{r['add_s']:.1f} | {r['add_s'] / r['full_s']:.3f} |\n"
              f"goal: <= 0.15 x the full build. Not counted in either: loading the scene (RGB-D fusion of "
              f"every frame, {r['scene_s']:.1f} s), which both need.")
    if "S2" in args.parts:
        rows = city_rows(args)
        print("\n| S2: city | prior | images | points | observations | render + build s | queries | points / query | "
              "LM iterations / query | s / query | x smallest | peak RSS MiB | x smallest | store MiB read / query | "
              "recall 25 cm, 2 deg | 1 m, 5 deg | accepted (beyond 25 cm, 2 deg) |")
        print("| --- | --- |" + " ---: |" * 15)
        for r in rows:
            rec = list(r["recall"].values())
            base = next(b for b in rows if b["prior"] == r["prior"])
            print(f"| {r['blocks']} | {r['prior']} | {r['images']} | {r['map_points']} | {r['observations']} | "
                  f"{r['render_s']:.0f} + {r['build_s']:.0f} | {r['queries']} | {r['points']:.0f} | "
                  f"{r['iterations']:.0f} | {r['s_per_query']:.2f} | "
                  f"{r['s_per_query'] / base['s_per_query']:.2f} | {r['peak_rss'] / 2**20:.0f} | "
                  f"{r['peak_rss'] / base['peak_rss']:.2f} | {r['bytes_per_query'] / 2**20:.2f} | "
                  f"{100 * (rec[0] or 0):.0f} % | {100 * (rec[1] or 0):.0f} % | "
                  f"{r['accepted']} ({r['accepted_beyond']}) |")
        for line in city_goals(rows):
            print("- " + line)
    if "S3" in args.parts:
        store_at_scale(args)
    return 0


def store_at_scale(args: argparse.Namespace) -> int:
    counts = {k: max(1, int(round(v * args.fraction))) for k, v in AACHEN.items()}
    conf = FeatureConfig(model="pixloc-lite0", image_scales=tuple(args.image_scales), dtype=args.dtype, pca=args.pca)
    store = args.work / (f"aachen-{args.fraction:g}-{args.dtype}-s{'-'.join(map(str, args.image_scales))}"
                         f"{f'-pca{args.pca}' if args.pca else ''}.zarr")
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"S3: a store of {counts['images']} images, {counts['points']} points, {counts['observations']} "
          f"observations ({args.fraction:g} x Aachen v1.1), {args.dtype}, image scales {args.image_scales}, "
          f"PCA {args.pca or 'off'} -> {store}")
    from pipeline.store.info import map_counts, observations_per_image
    from pipeline.store.feature_groups import finish_group
    if args.reuse and store.exists():
        assert map_counts(store)["num_images"] == counts["images"], "--reuse: another size"
        num_obs, gen_s, built = observations_per_image(store), float("nan"), None
        finish_group(store, conf)
    else:
        t0 = time.perf_counter()
        scene = synthetic_scene(counts["images"], counts["points"], counts["observations"], args.seed)
        gen_s = time.perf_counter() - t0
        built = build(store, scene, conf, args.seed)
        num_obs = np.bincount(scene.obs_image, minlength=len(scene.images))
        del scene
    files = [f for f in store.rglob("*") if f.is_file()]
    size = sum(f.stat().st_size for f in files)
    out = subprocess.run(command("read", store, json.dumps(conf.to_dict()), args.queries, args.seed),
                         capture_output=True, text=True, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    v2 = v2_figures(num_obs, len(args.image_scales))
    scale = 1 / args.fraction
    rows = [("bytes on disk", f"{size / 1e9:.2f} GB", f"{size * scale / 1e9:.2f} GB",
             f"{v2['bytes'] * scale / 1e9:.1f} GB",
             f"<= {GOALS['bytes'] / 1e9:.0f} GB", f"{size * scale / GOALS['bytes']:.2f}"),
            ("bytes per observation", f"{size / counts['observations']:.0f}", "same",
             f"{1047 / 2 * len(args.image_scales):.0f}", "<= 300",
             f"{size / counts['observations'] / 300:.2f}"),
            ("files", f"{len(files)}", f"{len(files) * scale:.0f}", f"{v2['files'] * scale:.0f}",
             f"<= {GOALS['files']}", f"{len(files) * scale / GOALS['files']:.2f}"),
            ("files per image", f"{len(files) / counts['images']:.1f}", "same",
             f"{v2['files'] / counts['images']:.0f}", "<= 20", f"{len(files) / counts['images'] / 20:.2f}"),
            ("time to open a reader", f"{r['open_s']:.2f} s", "", "", "", ""),
            ("reader RSS after open", f"{r['rss_open'] / 2**20:.0f} MiB (process before: "
             f"{r['rss_before'] / 2**20:.0f})", "", "", f"<= {GOALS['rss'] / 2**30:.0f} GiB per worker",
             f"{r['rss_open'] / GOALS['rss']:.2f}"),
            ("reader peak RSS (after the reads)", f"{r['peak_rss'] / 2**20:.0f} MiB", "", "", "", ""),
            ("reads of one query (3 references, cold)", f"{r['read_ms_median']:.1f} ms median, "
             f"{r['read_ms_p90']:.1f} ms p90 ({r['obs_per_query']} observations)", "", "", "", "")]
    if built:
        print(f"\nscene generated in {gen_s:.0f} s; structure written in {built['structure_s']:.0f} s; features of "
              f"{counts['images']} images in {built['features_s']:.0f} s ({built['images_per_s']:.1f} images/s, "
              "1 process)")
    print("\n| S3 | measured | at full size | v2 layout, full size | goal | measured / goal |")
    print("| --- | --- | --- | --- | --- | ---: |")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    return 0
