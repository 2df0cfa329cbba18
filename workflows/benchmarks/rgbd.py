"""Benchmark: time per query on an RGB-D map (7-Scenes stairs, the 7scenes preset), and where it
went (issue 12).

The map: sequences 2 and 3 of ``7scenes_stairs`` (TSDF points, as ``build-map 7scenes``; the preset's features: 1024 px,
image scales [4, 1]); the queries: sequences 1 and 4, from priors 20 cm and 5 deg off the ground
truth (seeded directions), so that every run starts from the same poses; references from
retrieval (top 10, 5 used), one residual per observation, 100 LM iterations per level, as the
preset. Three ways, in one process, in this order:

- ``baseline``: the official sampler (5 bilinear taps per point: value and central differences),
  every point at every level (the code before this benchmark's changes);
- ``gradient maps``: the central differences precomputed once per level and query
  (``pixloc.interpolation.append_gradient_maps``) at levels with at most 2 cells per point
  (``pixloc.optim.cost.use_gradient_maps``): the same gradients, 3 channel blocks sampled;
- ``+ points per cell``: and at most max(1,024, 1 x cells) residuals at a level (the 7scenes
  preset's ``points_per_cell: 1``): the coarse levels of a dense map hold tens of thousands of
  points in a few hundred cells.

Per way: seconds per query (each query's own total, so that a rerun reprints a finished way
from its records; the LM's share), residuals per level, the median error of the
refined poses (verification off, so that every refinement counts), and the largest pose
difference to the baseline.
"""

import argparse
import json
from pathlib import Path

import numpy as np

from pipeline.runtime import shared_folder

WAYS = (("baseline", False, 0.0), ("gradient maps", True, 0.0), ("+ points per cell 1", True, 1.0))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shared", type=Path, default=shared_folder(),
                   help="the shared data folder (default: $PIXLOC_SHARED, else ../shared)")
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-rgbd"), help="work folder (maps, runs)")
    p.add_argument("--queries", type=int, default=6, help="of the 6 test frames")


def priors(queries, path: Path, seed: int = 0) -> None:
    import cv2

    from pipeline.scene import rotmat_to_qvec
    rng = np.random.default_rng(seed)
    lines = []
    for q in queries:
        T = q.cam_from_world_gt
        axis, move = rng.normal(size=3), rng.normal(size=3)
        R = cv2.Rodrigues(np.deg2rad(5.0) * axis / np.linalg.norm(axis))[0] @ T[:, :3]
        centre = -T[:, :3].T @ T[:, 3] + 0.2 * move / np.linalg.norm(move)
        lines.append(" ".join([q.name, *map(str, rotmat_to_qvec(R)), *map(str, -R @ centre)]))
    path.write_text("\n".join(lines) + "\n")


def main(args: argparse.Namespace) -> int:
    from pipeline.mapping.build import build_map
    from pipeline.mapping.depth import rgbd_scene
    from pipeline.evaluate import pose_errors
    from pipeline.mapping.features import FeatureConfig
    from pipeline.localization.refine import LocalizerConfig
    from pipeline.mapping.readers.rgbd import read_7scenes
    from pipeline.localization.priors import OtherPipeline
    from pipeline.localization.retrieval import GlobalDescriptors
    from pipeline.models import localization_model
    from pipeline.localization.shard import LocalizationJob
    from pipeline.localization.verify import VerificationConfig
    from workflows.localize import plan_localization, run_sync
    from workflows.presets import load
    from pipeline.mapping.readers.sources import SevenScenes, load_queries

    root = args.shared / "data" / "7scenes_stairs"
    if not root.is_dir():
        raise SystemExit(f"benchmark rgbd: {root} not found (set --shared or PIXLOC_SHARED)")
    args.work.mkdir(parents=True, exist_ok=True)
    preset = load("7scenes")
    fconf = FeatureConfig(**{"dtype": "float16", **{k: tuple(v) if isinstance(v, list) else v
                                                   for k, v in preset["features"].items()}})
    store = args.work / "map.zarr"
    if not store.exists():
        build_map(rgbd_scene(read_7scenes(root, [2, 3]), method="tsdf"), store, fconf)  # build-map 7scenes
    queries = load_queries(SevenScenes.name, root, sequences=(1, 4))[:args.queries]
    priors(queries, args.work / "priors.txt")
    gt = {q.name: q.cam_from_world_gt for q in queries}
    refiner, _ = localization_model(fconf.model, "cpu")
    rows, base = [], None
    saved = [solver.interpolator.gradient_maps for solver in refiner.solvers]
    try:
        for name, gradient_maps, ppc in WAYS:
            for solver in refiner.solvers:  # this process's solvers, which the in-process run uses
                solver.interpolator.gradient_maps = gradient_maps
            lconf = LocalizerConfig(num_dbs=preset["localizer"]["num_dbs"], num_iters=preset["localizer"]["num_iters"],
                                    points_per_cell=ppc, verification=VerificationConfig(enabled=False))
            job = LocalizationJob(str(store), fconf, fconf.model, lconf, GlobalDescriptors(k=preset["retrieval"]["k"]),
                                  prior=OtherPipeline(prior_poses=str(args.work / "priors.txt")))
            # a finished run is reused (its records keep their timings): runs of the same job, one folder per way
            records = run_sync(plan_localization(job, queries, args.work / f"run-{len(rows)}"))
            elapsed = sum(r["timings"]["total"] for r in records)
            poses = {r["name"]: np.asarray(r["refined"]) for r in records}
            errors = np.array([pose_errors(poses[n], gt[n]) for n in poses])
            prior_err = np.array([pose_errors(np.asarray(r["prior"]), gt[r["name"]]) for r in records])
            lm = sum(v for r in records for k, v in r["timings"].items() if k.startswith("optim")) / len(records)
            diff = None if base is None else np.array([pose_errors(poses[n], base[n]) for n in poses]).max(0)
            base = base or poses
            rows.append({"way": name, "s_per_query": elapsed / len(records), "lm_s": lm,
                         "residuals": [lv["residuals"] for lv in records[0]["per_level"]],
                         "iterations": float(np.mean([r["iterations"] for r in records])),
                         "median": np.median(errors, 0).tolist(), "prior": np.median(prior_err, 0).tolist(),
                         "diff": None if diff is None else diff.tolist()})
            print(json.dumps(rows[-1]), flush=True)
    finally:  # they are this process's cached solvers: leave them as they were
        for solver, value in zip(refiner.solvers, saved):
            solver.interpolator.gradient_maps = value
    b = rows[0]["s_per_query"]
    print(f"\n7scenes_stairs, {len(queries)} queries from priors {rows[0]['prior'][0] * 100:.0f} cm / "
          f"{rows[0]['prior'][1]:.1f} deg off (median)\n")
    print("| way | s / query | x baseline | LM s / query | residuals per level (query 1: scale 4 coarse to fine, "
          "then scale 1) | LM iterations / query | median error, refined | largest difference to baseline |")
    print("| --- | ---: | ---: | ---: | --- | ---: | --- | --- |")
    for r in rows:
        d = "-" if r["diff"] is None else f"{r['diff'][0] * 100:.2f} cm, {r['diff'][1]:.3f} deg"
        print(f"| {r['way']} | {r['s_per_query']:.1f} | {r['s_per_query'] / b:.2f} | {r['lm_s']:.1f} | "
              f"{', '.join(map(str, r['residuals']))} | {r['iterations']:.0f} | "
              f"{r['median'][0] * 100:.1f} cm, {r['median'][1]:.2f} deg | {d} |")
    return 0
