"""Benchmark: a sequence's chunks localized as one body each, against its frames one by one.

The accuracy benchmark's maps and queries (``workflows.benchmarks.accuracy``: the same splits, features
and work folder, so that its maps are reused): the queries of a scene, in name order, are a sequence (every
other frame of a capture). Its odometry is simulated from the ground truth with drift: each step's relative
motion gets Gaussian noise of ``--drift`` times its length on each translation axis and of ``--drift`` times
its angle (at least 0.01 deg) about a random axis, seeded, accumulated along the sequence, and written as an
odometry file (``pipeline.rigs.read_odometry`` reads it back into chunks of ``--chunk`` frames). Both ways
use the accuracy benchmark's job with the top-1 prior: ``single``, each frame alone
(``pipeline.localization.shard.localize_queries``); ``chunk``, each chunk as one body
(``pipeline.localization.rigs.localize_frames``). Rows as the accuracy benchmark's (recall at fractions of the
scene's scale, medians, verified and wrong), per scene and pooled.
"""

import argparse
import json
import math
from pathlib import Path
from typing import Dict, List

import numpy as np

SCENES = ("beer", "templeRing", "dino")  # captures whose queries in name order are a sequence


def add_arguments(p: argparse.ArgumentParser) -> None:
    from . import accuracy
    accuracy.add_arguments(p)
    p.add_argument("--chunk", type=int, default=5, help="frames per chunk (default 5)")
    p.add_argument("--drift", type=float, default=0.01, help="the odometry's drift per step, as a fraction of the "
                   "step's motion (default 0.01)")
    p.add_argument("--seed", type=int, default=0, help="the odometry noise's seed")
    p.add_argument("--rules", nargs="+", default=["half", "any", "pooled"], choices=["half", "any", "pooled"],
                   help="when a chunk is verified (pipeline.localization.rigs.BODY_RULES), each a row")
    p.set_defaults(func=main, scenes=list(SCENES), work=Path("outputs/benchmark-accuracy"))


def simulated_odometry(poses: List[np.ndarray], drift: float, seed: int) -> List[np.ndarray]:
    """cam_from_odom of each frame (see the module docstring); the first frame's is its ground truth."""
    import torch
    from pixloc.geometry import lie
    from pipeline.localization.bodies import compose, invert
    rng = np.random.default_rng(seed)
    out = [np.asarray(poses[0], np.float64)]
    for a, b in zip(poses[:-1], poses[1:]):
        step = compose(b, invert(a))  # cam_b_from_cam_a
        angle = math.acos(np.clip((np.trace(step[:, :3]) - 1) / 2, -1, 1))
        axis = rng.normal(size=3)
        noise_R = lie.so3_exp(torch.from_numpy(axis / np.linalg.norm(axis) * math.radians(
            max(drift * math.degrees(angle), 0.01)) * abs(rng.normal()))).numpy()
        noise_t = rng.normal(size=3) * drift * np.linalg.norm(step[:, 3]) / math.sqrt(3)
        noisy = np.concatenate([noise_R @ step[:, :3], (step[:, 3] + noise_t)[:, None]], 1)
        out.append(compose(noisy, out[-1]))
    return out


def main(args: argparse.Namespace) -> int:
    from pipeline.localization.priors import Top1
    from pipeline.localization.refine import LocalizerConfig
    from pipeline.localization.results import result_to_record
    from pipeline.localization.retrieval import GlobalDescriptors
    from pipeline.localization.shard import LocalizationJob
    from pipeline.mapping.features import FeatureConfig
    from pipeline.rigs import read_odometry
    from pipeline.scene import rotmat_to_qvec
    from .rigs import one_by_one_and_as_bodies
    from .accuracy import OWN_SPLITS, SPLITS, pooled, row, scene_parts, scene_scale, table

    fconf = FeatureConfig(model=args.model, resize=args.resize, image_scales=(1,), sift=args.sift,
                          dtype=args.dtype, pca=args.pca, descriptor=args.descriptor)
    args.work.mkdir(parents=True, exist_ok=True)
    settings = args.work / "features.json"
    if settings.exists() and not fconf.made(json.loads(settings.read_text())):
        raise SystemExit(f"pixloc: error: {args.work} holds maps of features {settings.read_text().strip()}: "
                         "give the same feature options, or another --work")
    settings.write_text(json.dumps(fconf.to_dict()) + "\n")
    rows: List[Dict] = []
    for key in args.scenes:
        parts = scene_parts(key, args, fconf)
        scale = scene_scale(parts[0][1])
        metric = OWN_SPLITS[key] if key in OWN_SPLITS else SPLITS[key].metric
        ways = ["single"] + [f"chunk-{rule}" for rule in args.rules]
        records: Dict[str, List[Dict]] = {way: [] for way in ways}
        seconds = {way: 0.0 for way in ways}
        gt = {}
        for name, store, queries in parts:
            queries = sorted(queries, key=lambda q: q.name)
            gt.update({q.name: q.cam_from_world_gt for q in queries})
            odometry = simulated_odometry([q.cam_from_world_gt for q in queries], args.drift, args.seed)
            path = args.work / "sequences" / f"{name}.odometry.txt"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("".join(f"{q.name} " + " ".join(f"{v:.12g}" for v in (*rotmat_to_qvec(T[:, :3]), *T[:, 3]))
                                    + "\n" for q, T in zip(queries, odometry)))
            frames = read_odometry(path, queries, args.chunk)
            job = LocalizationJob(str(store), fconf, fconf.model, LocalizerConfig(num_dbs=3, num_iters=50),
                                  GlobalDescriptors(k=5), prior=Top1())
            single, chunks, spent = one_by_one_and_as_bodies(job, queries, frames, args.rules)
            records["single"] += [result_to_record(r) for r in single]
            seconds["single"] += spent["single"]
            for rule in args.rules:
                records[f"chunk-{rule}"] += [result_to_record(r) for f in chunks[rule] for r in f.images]
                seconds[f"chunk-{rule}"] += spent[rule]
        for way in records:
            rows.append(row(key, way, records[way], gt, scale, metric, seconds[way]))
            (args.work / "sequences" / f"{key}-{way}.jsonl").write_text(
                "".join(json.dumps(r) + "\n" for r in records[way]))
        print(table([r for r in rows if r["scene"] == key]), flush=True)
    rows += pooled(rows)
    print("\n" + table(rows))
    print(f"\nchunks of {args.chunk} frames, odometry drift {100 * args.drift:g} % per step (seed {args.seed})")
    out = args.work / f"sequences-chunk{args.chunk}.json"
    out.write_text(json.dumps(rows, indent=1))
    print(f"written: {out}")
    return 0
