"""Benchmark: a rig localized as one body against its images localized one by one.

The demo's scene and map (``pixloc demo``: the generated courtyard, seed 7, its map from depth and known
poses, the shipped model's features), and a three-camera rig (``pipeline.data.rigs``: 55 degrees and 15
cm apart) rendered at the demo's query poses of each condition (day, dusk, night, occluded). Both ways
use the demo's job (retrieval among the images of the query's area, the top-1 reference's pose as the
prior, 3 references, 50 LM iterations): ``single``, every image as a query of its own
(``pipeline.localization.shard.localize_queries``, as ``pixloc localize`` runs it); ``rig``, each frame
as one body (``pipeline.localization.rigs.localize_frames``). Per condition: each image's recall at the
demo's thresholds (its reported pose: refined where verified, else its prior), the frames verified and
the verified frames whose rig pose is wrong (beyond (0.25 m, 2 deg), and beyond (1 m, 5 deg)), and the
seconds per image of each way.
"""

import argparse
import json
import time
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-rigs"), help="work folder (scene and map)")
    p.add_argument("--frames-per-condition", type=int, default=5, help="rig frames per condition")
    p.add_argument("--model", default="pixloc-lite0", help="feature model (default: the shipped pixloc-lite0)")
    p.add_argument("--rules", nargs="+", default=["half", "any", "pooled"], choices=["half", "any", "pooled"],
                   help="when a frame is verified (pipeline.localization.rigs.BODY_RULES), each a row")
    p.set_defaults(func=main)


def frame_errors(frames, results) -> List[Dict]:
    """Per frame: its condition, whether it is verified, and its rig pose's error (m, deg)."""
    from pipeline.evaluate import pose_errors
    out = []
    for frame, r in zip(frames, results):
        t, R = pose_errors(r.pose, frame.body_gt())
        out.append({"key": frame.key, "condition": frame.tags["condition"], "verified": r.success,
                    "verified_images": len(r.verified_by), "start": r.start, "reason": r.reason,
                    "error_t": t if np.isfinite(t) else None, "error_R": R if np.isfinite(R) else None})
    return out


def one_by_one_and_as_bodies(job, images, frames, rules: Sequence[str] = ("half",)
                             ) -> Tuple[List, Dict[str, List], Dict[str, float]]:
    """``images`` localized one by one (``localize_queries``) and ``frames`` as bodies (``localize_frames``) with
    each of ``rules``, in this process on one thread: (their QueryResults, the FrameResults per rule, the seconds
    of each way: ``single`` and each rule)."""
    from pipeline.localization.refine import Localizer
    from pipeline.localization.rigs import localize_frames
    from pipeline.localization.shard import localize_queries
    from pipeline.models import localization_model
    from pipeline.runtime import torch_threads
    from pipeline.store.reader import open_reader
    bodies, seconds = {}, {}
    with torch_threads(1):
        refiner, digest = localization_model(job.model, job.device)
        reader = open_reader(job.store, job.features, digest)
        localizer = Localizer(refiner.extractor, refiner.solvers, reader, job.localizer, job.device)
        print(f"      {len(images)} images one by one ...", flush=True)
        t0 = time.perf_counter()
        single = localize_queries(job, reader, localizer, images)
        seconds["single"] = time.perf_counter() - t0
        for rule in rules:
            print(f"      {len(frames)} frames as bodies (a body verified by the {rule!r} rule) ...", flush=True)
            t0 = time.perf_counter()
            bodies[rule] = localize_frames(job, reader, localizer, frames, rule)
            seconds[rule] = time.perf_counter() - t0
    return single, bodies, seconds


def run(work: Path, frames_per_condition: int, model: str, num_references: int = 30, queries_per_condition: int = 1,
        seed: int = None, rules: Sequence[str] = ("half",)) -> Dict:
    """The benchmark in ``work`` (the demo's scene and map there, as ``pixloc demo`` makes them with
    ``num_references`` and ``queries_per_condition``; reused where they are)."""
    from pipeline.data.rigs import generate_rig_frames, read_rig_frames
    from pipeline.data.synthetic import SyntheticConfig, ensure_generated, read_synthetic
    from pipeline.evaluate import evaluate
    from pipeline.localization.priors import Top1
    from pipeline.localization.refine import LocalizerConfig
    from pipeline.localization.results import result_to_record
    from pipeline.localization.retrieval import GlobalDescriptors
    from pipeline.localization.rigs import Frame
    from pipeline.localization.shard import LocalizationJob
    from workflows.demo_scene import DEMO_CAMERA, DEMO_SEED, DEMO_THRESHOLDS, demo_map

    work = Path(work).resolve()
    seed = DEMO_SEED if seed is None else seed
    root = work / "scene"
    ensure_generated(root, SyntheticConfig(seed=seed), num_references, queries_per_condition, DEMO_CAMERA,
                     query_spread=0.5)
    mapping, _ = read_synthetic(root)
    store, fconf = demo_map(work, mapping, model, seed)
    generate_rig_frames(root, SyntheticConfig(seed=seed), DEMO_CAMERA, frames_per_condition)
    frames = [Frame(key, tuple(queries), tuple(cams), {"condition": condition})
              for key, condition, queries, cams in read_rig_frames(root, DEMO_CAMERA)]
    images = [q for f in frames for q in f.queries]
    job = LocalizationJob(str(store), fconf, model, LocalizerConfig(num_dbs=3, num_iters=50),
                          GlobalDescriptors(k=5, same_tag="area"), prior=Top1())
    gt = {q.name: q.cam_from_world_gt for q in images}
    out: Dict = {"frames": len(frames), "cameras": len(frames[0].queries), "thresholds": DEMO_THRESHOLDS,
                 "ways": ["single"] + [f"rig-{rule}" for rule in rules]}
    single, bodies, seconds = one_by_one_and_as_bodies(job, images, frames, rules)
    out["seconds_per_image"] = {("single" if k == "single" else f"rig-{k}"): v / len(images)
                                for k, v in seconds.items()}
    tags = {q.name: q.tags for q in images}
    ways = [("single", single)] + [(f"rig-{rule}", [r for f in bodies[rule] for r in f.images]) for rule in rules]
    for way, results in ways:
        records = [result_to_record(r, tags[r.name]) for r in results]
        out[way] = evaluate(records, gt, DEMO_THRESHOLDS, tag_keys=["condition"])
    out["frames_detail"] = {f"rig-{rule}": frame_errors(frames, bodies[rule]) for rule in rules}
    return out


def format_table(out: Dict) -> str:
    keys = [f"recall@{t}m,{r}deg" for t, r in out["thresholds"]]
    head = f"{'condition':<20} {'way':<11} {'n':>3}  " + "  ".join(f"{k[7:]:>12}" for k in keys) + \
        "  frames verified  verified wrong (0.25 m, 2 deg / 1 m, 5 deg)"
    lines = [head, "-" * len(head)]
    for group in out["single"]:
        for way in out["ways"]:
            s = out[way][group]["refined"]
            row = f"{group:<20} {way:<11} {s['count']:>3}  " + "  ".join(f"{100 * s[k]:>11.0f}%" for k in keys)
            if way != "single":
                cond = group.split("=", 1)[1] if "=" in group else None
                fr = [d for d in out["frames_detail"][way] if cond is None or d["condition"] == cond]
                ver = [d for d in fr if d["verified"]]
                wrong = [sum(1 for d in ver if d["error_t"] is None or d["error_t"] > t or d["error_R"] > r)
                         for t, r in ((0.25, 2), (1, 5))]
                row += f"  {len(ver):>4} of {len(fr):<4}    {wrong[0]} / {wrong[1]}"
            lines.append(row)
    s = out["seconds_per_image"]
    lines.append("seconds per image: " + ", ".join(f"{way} {s[way]:.2f}" for way in out["ways"])
                 + "; " + ", ".join(f"{way} / single {s[way] / s['single']:.2f}" for way in out["ways"][1:]))
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    out = run(args.work, args.frames_per_condition, args.model, rules=args.rules)
    print(format_table(out))
    path = Path(args.work) / "rigs.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"\nwritten: {path}")
    return 0
