"""Benchmark: what int8 (and PCA) feature storage saves on disk, and what it costs in localization.

For each scene and storage type (``--storage``: ``float16``, the default, and ``int8``; a PCA of D
components as ``int8-pcaD``; SIFT descriptors stored for the sift prior as ``-siftN`` after
either), at ``--image-scales`` (default 1), the same map is built (leave-one-out on Strecha
fountain-P11 and Herz-Jesus-P8, the demo scene, 7scenes_stairs; the triangulations and the demo
scene of the verification benchmark in ``--work`` are reused) and
its queries are localized from retrieval (top-1 prior, verification on). Per scene and type:
bytes on disk per observation (the feature group, and the whole store), files per image, and
recall at (5 cm, 1 deg), (25 cm, 2 deg), (1 m, 5 deg), with the change from float16 in points.

``oracle``: the official localization cases (../shared/oracle, official checkpoint with random
weights) with float32, float16 and int8 storage: how many cases end within the parity
tolerance of the official pose (the test of tests/pipeline/test_localize_parity.py), and the recall
against the cases' SfM poses (``T_gt``) at (2.5 %, 2 deg) and (10 %, 5 deg) of the median camera-to-point
distance (the Sacre Coeur thresholds of the search benchmark), for each storage and for the official poses.
Stores and runs are kept in ``--work``/storage: a rerun reprints.
"""

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Dict, List

import numpy as np

from pipeline.runtime import shared_folder
from pipeline.evaluate import evaluate, fmt
from pipeline.mapping.features import FeatureConfig
from pipeline.localization.refine import LocalizerConfig
from pipeline.localization.retrieval import GlobalDescriptors
from pipeline.localization.shard import LocalizationJob
from pipeline.store.feature_groups import feature_key
from pipeline.store.info import map_counts
from pixloc.nets.registry import DEFAULT_MODEL

from ..localize import plan_localization, run_sync
from .verification import demo_map, seven_scenes_map, strecha_maps

THRESHOLDS = ((0.05, 1.0), (0.25, 2.0), (1.0, 5.0))
SCENES = ("fountain", "herzjesus", "demo", "7scenes", "sacre_coeur", "oracle")
DTYPES = ("float16", "int8")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shared", type=Path, default=shared_folder(),
                   help="the shared data folder (default: $PIXLOC_SHARED, else ../shared)")
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-verification"),
                   help="the verification benchmark's folder (its triangulations are reused); stores and "
                        "runs go to WORK/storage")
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES, help="scenes to run")
    p.add_argument("--storage", nargs="+", default=list(DTYPES), metavar="TYPE",
                   help="storage types compared with the first: float16, int8, float32, optionally with a PCA "
                        "of D components as TYPE-pcaD (e.g. int8-pca48), and SIFT descriptors stored for the sift "
                        "prior with -siftN (e.g. float16-sift1600); default float16 int8")
    p.add_argument("--image-scales", type=int, nargs="+", default=[1],
                   help="image scales of the maps (default 1; the official multiscale is 4 1, with --resize 1024: "
                        "at 512, the coarse image is too small for the coarsest level)")
    p.add_argument("--resize", type=int, default=512, help="longer image side of the Strecha maps (default 512; "
                   "the demo and 7-Scenes keep 320, Sacre Coeur 1024)")


def _parts(args, key: str, fconf: FeatureConfig, stores: Path):
    if key == "fountain":
        return strecha_maps(args.shared, args.work, "fountain-P11", ["0002.jpg", "0004.jpg", "0006.jpg", "0008.jpg"],
                        fconf, stores)
    if key == "herzjesus":
        return strecha_maps(args.shared, args.work, "Herz-Jesus-P8", ["0002.jpg", "0003.jpg", "0004.jpg", "0005.jpg"],
                        fconf, stores)
    if key == "demo":
        return demo_map(args.work, fconf, stores)
    if key == "sacre_coeur":  # each oracle query photo against the other 9, and the night photo against all 10
        from .sacre_coeur import sacre_coeur
        return sacre_coeur(args.shared, stores, dataclasses.replace(fconf, resize=1024))
    return seven_scenes_map(args.shared, args.work, fconf, stores)


def store_bytes(store: Path, conf: FeatureConfig) -> Dict[str, float]:
    """Bytes on disk per observation (feature group; whole store) and files per image."""
    meta = map_counts(store)
    files = [f for f in store.rglob("*") if f.is_file()]
    group = store / "features" / feature_key(conf)
    n_obs, n_img = max(meta["num_observations"], 1), max(meta["num_images"], 1)
    return {"observations": meta["num_observations"], "images": meta["num_images"],
            "features_B": sum(f.stat().st_size for f in files if f.is_relative_to(group)) / n_obs,
            "store_B": sum(f.stat().st_size for f in files) / n_obs, "files": len(files) / n_img}


def storage_config(base: FeatureConfig, variant: str) -> FeatureConfig:
    """``TYPE``, ``TYPE-pcaD``, with ``-siftN`` after either -> the feature config with that storage."""
    variant, _, sift = variant.partition("-sift")
    dtype, _, pca = variant.partition("-pca")
    return dataclasses.replace(base, dtype=dtype, pca=int(pca or 0), sift=int(sift or 0))


def scene_rows(args, key: str) -> List[Dict]:
    scales, resize = tuple(getattr(args, "image_scales", (1,))), getattr(args, "resize", 512)
    base = FeatureConfig(model=DEFAULT_MODEL, resize=resize, image_scales=scales, dtype="float16")
    lconf = LocalizerConfig(num_dbs=3, num_iters=50)
    rows = []
    suffix = ("" if scales == (1,) else "-s" + "-".join(map(str, scales))) + ("" if resize == 512 else f"-r{resize}")
    for dtype in getattr(args, "storage", DTYPES):
        stores = args.work / "storage" / f"{dtype}{suffix}"
        stores.mkdir(parents=True, exist_ok=True)
        records, gt, sizes = [], {}, []
        for name, store, queries in _parts(args, key, storage_config(base, dtype), stores):
            from pipeline.store.info import feature_config as store_feature_config
            conf = store_feature_config(store)
            job = LocalizationJob(str(store), conf, conf.model, lconf,
                                  GlobalDescriptors(k=5, same_tag="area" if key == "demo" else None))
            out = args.work / "storage" / "runs" / f"{dtype}{suffix}" / name.replace("/", "-")
            records += run_sync(plan_localization(job, queries, out, shard_size=8))
            gt.update({q.name: q.cam_from_world_gt for q in queries})
            sizes.append(store_bytes(store, conf))
        s = evaluate(records, gt, THRESHOLDS)["all"]["refined"]
        n_obs = sum(x["observations"] for x in sizes)
        rows.append({"scene": key, "dtype": dtype, "queries": s["count"], "maps": len(sizes),
                     "features_B": sum(x["features_B"] * x["observations"] for x in sizes) / n_obs,
                     "store_B": sum(x["store_B"] * x["observations"] for x in sizes) / n_obs,
                     "files": float(np.mean([x["files"] for x in sizes])),
                     **{k: v for k, v in s.items() if k.startswith("recall@")}})
    return rows


def oracle_rows(args) -> List[Dict]:
    """The official localization cases with each storage type: cases within the parity tolerance."""
    import torch

    from pipeline.mapping.build import build_map
    from pipeline.localization.refine import Localizer
    from pipeline.store.reader import MapReader
    from pipeline.queries import read_queries_with_intrinsics
    from pipeline.textfiles import read_pairs
    from pipeline.mapping.readers.colmap import read_colmap
    from pipeline.localization.verify import VerificationConfig
    from pixloc.geometry import Pose
    from pixloc.nets.registry import load_refiner

    oracle = args.shared / "oracle"
    ckpt = oracle / "official_megadepth_random" / "checkpoint_best.tar"
    if not ckpt.is_file():
        print(f"oracle: {ckpt} is not there: skipped")
        return []
    cases = json.loads((oracle / "localization_cases.json").read_text())
    images = args.shared / "data" / "sacre_coeur" / "mapping"
    scene = read_colmap(oracle / "sacre_coeur_sfm", images)
    queries = {q.name: q for q in read_queries_with_intrinsics(oracle / "queries_with_intrinsics.txt", images)}
    pairs = read_pairs(oracle / "pairs.txt")
    refiner = load_refiner(str(ckpt))

    def pose(values) -> Pose:
        return Pose(torch.tensor(values, dtype=torch.float64).reshape(12))

    from .sacre_coeur import night_reference

    unit = night_reference()["median_camera_to_point_distance"] / 100  # 1 % of the median distance
    thresholds = ((2.5 * unit, 2.0), (10 * unit, 5.0))

    def gt_error(T: Pose, expected) -> tuple:
        dR, _ = (T @ pose(expected["T_gt"]).inv()).magnitude()
        return float((T.center - pose(expected["T_gt"]).center).norm()), float(dR)

    def recalls(errors) -> List[int]:
        return [sum(e[0] <= t and e[1] <= r for e in errors) for t, r in thresholds]

    official_errors = [gt_error(pose(expected["T_refined"]), expected)
                       for config in ("noavg", "avg") for expected in cases[config]["results"].values()]
    rows = [{"dtype": "official", "within": None, "cases": len(official_errors), "median_dc": 0.0,
             "features_B": None, "gt_recall": recalls(official_errors)}]
    for dtype in ("float32", "float16", "int8"):
        within, total, dcs, errors = 0, 0, [], []
        for config in ("noavg", "avg"):
            conf = cases[config]["conf"]
            refinement = conf["refinement"]
            fconf = FeatureConfig(str(ckpt), conf["features"]["preprocessing"]["resize"],
                                  tuple(refinement["multiscale"] or [1]), conf["optimizer"]["pad"], dtype)
            store = args.work / "storage" / "oracle" / f"{config}-{dtype}.zarr"
            build_map(scene, store, fconf)
            reader = MapReader(store, fconf, refiner.feature_digest())
            localizer = Localizer(refiner.extractor, refiner.solvers, reader, LocalizerConfig(
                num_dbs=refinement["num_dbs"], average_observations=refinement["average_observations"],
                num_iters=conf["optimizer"]["num_iters"], verification=VerificationConfig(enabled=False)))
            for name, expected in cases[config]["results"].items():
                dbs = [reader.index[n] for n in pairs[name][:refinement["num_dbs"]]]
                result = localizer.localize(queries[name], dbs, reader.cam_from_world[dbs[0]])
                total += 1
                if result.refined is None:  # failed where the official code did not: not within
                    dcs.append(float("inf"))
                    errors.append((float("inf"), float("inf")))
                    continue
                T = torch.as_tensor(np.asarray(result.refined), dtype=torch.float64)
                ours = Pose.from_Rt(T[:, :3], T[:, 3])
                official, init = pose(expected["T_refined"]), pose(expected["T_init"])
                moved_R, _ = (official @ init.inv()).magnitude()
                moved_c = float((official.center - init.center).norm())
                dR, _ = (ours @ official.inv()).magnitude()
                dc = float((ours.center - official.center).norm())
                within += dc <= max(2e-3, 0.1 * moved_c) and float(dR) <= max(0.01, 0.1 * float(moved_R))
                dcs.append(dc)
                errors.append(gt_error(ours, expected))
            sizes = store_bytes(store, fconf)
        rows.append({"dtype": dtype, "within": within, "cases": total, "median_dc": float(np.median(dcs)),
                     "features_B": sizes["features_B"], "gt_recall": recalls(errors)})
    return rows


def main(args: argparse.Namespace) -> int:
    rows = [r for key in args.scenes if key != "oracle" for r in scene_rows(args, key)]
    if rows:
        print(table(rows))
    if "oracle" in args.scenes:
        print()
        print("| oracle cases, official checkpoint | storage | cases within the parity tolerance | median |c - "
              "c_official| | feature bytes / observation (last config) | within (2.5 %, 2 deg) of T_gt | "
              "within (10 %, 5 deg) of T_gt |")
        print("| --- | --- | ---: | ---: | ---: | ---: | ---: |")
        for r in oracle_rows(args):
            within = "-" if r["within"] is None else f"{r['within']} / {r['cases']}"
            size = "-" if r["features_B"] is None else f"{r['features_B']:.0f}"
            print(f"| Sacre Coeur | {r['dtype']} | {within} | {r['median_dc']:.2e} | {size} | "
                  + " | ".join(f"{n} / {r['cases']}" for n in r["gt_recall"]) + " |")
    return 0


def table(rows: List[Dict]) -> str:
    keys = [k for k in rows[0] if k.startswith("recall@")]
    lines = ["| scene | storage | maps | queries | feature B / obs | store B / obs | files / image | "
             + " | ".join(k[len("recall@"):] for k in keys) + " |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | " + " | ".join("---:" for _ in keys) + " |"]
    base = {}
    for r in rows:  # the first storage type of each scene is the baseline
        base.setdefault(r["scene"], r)
    for r in rows:
        b = base.get(r["scene"])
        cells = []
        for k in keys:
            cell = f"{fmt(100 * r[k] if r[k] is not None else None, '.0f')} %"
            if b is not r and b and r[k] is not None and b[k] is not None:
                cell += f" ({100 * (r[k] - b[k]):+.0f})"
            cells.append(cell)
        ratio = f" ({r['features_B'] / b['features_B']:.2f}x)" if b and b is not r else ""
        lines.append(f"| {r['scene']} | {r['dtype']} | {r['maps']} | {r['queries']} | {r['features_B']:.0f}{ratio} | "
                     f"{r['store_B']:.0f} | {r['files']:.1f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
