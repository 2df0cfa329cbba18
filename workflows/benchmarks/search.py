"""Benchmark: the ``search`` prior against ``top1``, ``average`` and ``hypotheses``, from retrieval.

On the scenes of the verification benchmark (Strecha fountain-P11 and Herz-Jesus-P8 leave-one-out,
the demo scene, 7scenes_stairs; their maps are built once in ``--work`` and shared with it), every
query is localized from retrieval with each prior, verification on (the reported pose: the refined
one if verified, else the prior). Per scene and prior: the median error of the prior (top-1
reference), recall at (5 cm, 1 deg), (25 cm, 2 deg), (1 m, 5 deg), and wall time per query in this
process (one thread), with its ratio to ``top1``. Runs are kept in ``--work``: a rerun reprints.
``--priors ... truth`` adds a refinement from each query's ground-truth pose (``--prior poses``),
scored on the refined pose whether verified or not: what the model reaches on that map from a
perfect start, the most that any prior can give. ``sift`` adds the SIFT + PnP prior refined by
PixLoc, and beside it the row ``sift-pnp``: the SIFT + PnP peer alone (its pose where PnP found one,
no pose elsewhere), from the same runs.
"""

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from pipeline.runtime import shared_folder
from pipeline.evaluate import evaluate, fmt
from pipeline.mapping.features import FeatureConfig
from pipeline.localization.refine import LocalizerConfig
from pipeline.localization.priors import PRIORS, Average, OtherPipeline, ReferenceHypotheses, Search, Sift, Top1
from pipeline.localization.retrieval import GlobalDescriptors, RetrievalSettings
from pipeline.localization.shard import LocalizationJob
from pipeline.localization.verify import CHI2_6DOF_99
from pipeline.localization.sift import pnp_pose_found

from pixloc.nets.registry import DEFAULT_MODEL

from ..build_map import plan_build, run_sync as build_sync
from ..localize import plan_localization, run_sync
from .sacre_coeur import sacre_coeur
from .verification import demo_map, seven_scenes_map, strecha_maps, write_priors

THRESHOLDS = ((0.05, 1.0), (0.25, 2.0), (1.0, 5.0))
# rows that run the sift prior with parts of its refinement of PnP poses off or on: (the PnP inliers'
# reprojection term's weight, verification's max_keypoint_chi2), against sift's defaults (the term, no gate)
SIFT_VARIANTS = {
    "sift-features": (0.0, 0.0),  # the features alone, nothing kept: the refinement before the keypoint term
    "sift-gate": (0.0, CHI2_6DOF_99),  # the features alone, the PnP pose kept where they leave it
    "sift-joint-gate": (Sift.keypoint_weight, CHI2_6DOF_99),  # both terms in the cost, and the gate
}


def sift_variant(job: LocalizationJob, name: str) -> LocalizationJob:
    """``job`` with the sift prior run as the row ``name`` of ``SIFT_VARIANTS`` runs it."""
    weight, gate = SIFT_VARIANTS[name]
    verification = dataclasses.replace(job.localizer.verification, max_keypoint_chi2=gate)
    return dataclasses.replace(job, prior=Sift(keypoint_weight=weight),
                               localizer=dataclasses.replace(job.localizer, verification=verification))
FROM_RETRIEVAL = [name for name, entry in PRIORS.items() if entry.retrieves and not entry.inputs]  # no file needed
SCENES = ("fountain", "herzjesus", "demo", "7scenes", "sacre_coeur", "sacre_coeur_night", "virtual_gallery")
# the official localization setting of the Sacre Coeur cases (oracle/localization_cases.json, avg)
SACRE_COEUR_FEATURES = FeatureConfig(model=DEFAULT_MODEL, resize=1024, image_scales=(4, 1), dtype="float16")
HELD_OUT = {"fountain": ("fountain-P11", ["0002.jpg", "0004.jpg", "0006.jpg", "0008.jpg"]),
            "herzjesus": ("Herz-Jesus-P8", ["0002.jpg", "0003.jpg", "0004.jpg", "0005.jpg"])}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shared", type=Path, default=shared_folder(),
                   help="the shared data folder (default: $PIXLOC_SHARED, else ../shared)")
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-verification"),
                   help="maps and runs (default: the verification benchmark's folder, whose maps it reuses)")
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES, help="scenes to run")
    p.add_argument("--priors", nargs="+", default=[Top1.name, Average.name, ReferenceHypotheses.name, Search.name],
                   choices=[*FROM_RETRIEVAL, "truth"],
                   help="truth: refine from the ground-truth pose (prior poses), the most any prior can reach; "
                        "sift: SIFT + PnP refined, with the peer SIFT + PnP alone as the row sift-pnp")


def _sources(args, fconf):
    for key in args.scenes:
        if key in HELD_OUT:
            folder, names = HELD_OUT[key]
            yield key, list(strecha_maps(args.shared, args.work, folder, names, fconf))
        elif key == "demo":
            yield key, list(demo_map(args.work, fconf))
        elif key == "7scenes":
            yield key, list(seven_scenes_map(args.shared, args.work, fconf))
        elif key in ("sacre_coeur", "sacre_coeur_night"):
            yield key, sacre_coeur(args.shared, args.work, SACRE_COEUR_FEATURES, night=key == "sacre_coeur_night",
                                   day=key == "sacre_coeur")
        elif key == "virtual_gallery":
            yield key, list(virtual_gallery_map(args.shared, args.work, fconf))
        else:
            raise ValueError(f"Unknown scene {key!r}: use {', '.join(SCENES)}.")


def virtual_gallery_map(shared: Path, work: Path, fconf):
    from pipeline.mapping.readers.colmap import triangulate_known_poses
    from pipeline.mapping.readers.kapture import read_kapture
    from pipeline.mapping.readers.sources import Kapture, load_queries
    from .verification import store_complete
    root = shared / "data" / "virtual_gallery"
    store = work / "virtual_gallery.zarr"
    if not store_complete(store, fconf):
        scene = triangulate_known_poses(read_kapture(root / "mapping"), root / "mapping" / "sensors" / "records_data",
                                        work / "virtual_gallery.work")
        build_sync(plan_build(scene, store, fconf))
    yield "virtual_gallery", store, load_queries(Kapture.name, root / "query")


def _truth_file(queries, out: Path) -> Path:
    """The queries' ground-truth poses, as a prior poses file next to the run ``out``."""
    path = out.parent / "truth-poses.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_priors(path, {q.name: np.asarray(q.cam_from_world_gt, np.float64) for q in queries})
    return path


def localize_priors(parts, priors: List[str], runs: Path, lconf: LocalizerConfig, retrieval: RetrievalSettings,
                    descriptor: Optional[str] = None) -> Tuple[Dict[str, Dict], Dict[str, np.ndarray]]:
    """Every (name, store, queries) part of a scene localized with each prior (runs kept in
    ``runs/NAME/PRIOR``: a rerun reads them back). Returns {prior: {"records", "time"}} (``time``:
    the runs' wall seconds; with ``sift`` also the peer ``sift-pnp``, its time that of the sift
    runs' stages before the LM) and the queries' ground truth. ``descriptor``: the feature group of
    that global descriptor, where a store has several."""
    from pipeline.store.info import feature_configs
    per_prior: Dict[str, Dict] = {p: {"records": [], "time": 0.0} for p in priors}
    gt = {}
    for name, store, queries in parts:
        configs = feature_configs(store)
        conf = next((c for c in configs if c.descriptor == descriptor), configs[0])
        gt.update({q.name: q.cam_from_world_gt for q in queries})
        base = LocalizationJob(str(store), conf, conf.model, lconf, retrieval)
        for prior in priors:
            out = runs / name.replace("/", "-") / prior
            if prior == "truth":
                job = dataclasses.replace(base, prior=OtherPipeline(prior_poses=str(_truth_file(queries, out))))
            elif prior in SIFT_VARIANTS:
                job = sift_variant(base, prior)
            else:
                job = dataclasses.replace(base, prior=PRIORS.entry(prior)())
            plan = plan_localization(job, queries, out, shard_size=8)
            t0 = time.perf_counter()
            records = run_sync(plan)
            elapsed = time.perf_counter() - t0
            if plan.todo:  # timed now; a rerun reads the time of the run that made them
                (out / "wall_s.txt").write_text(f"{elapsed:.3f}\n")
            if prior == "truth":  # the refined pose itself, verified or not (a rejected one keeps the truth)
                records = [dict(r, success=r["refined"] is not None) for r in records]
            per_prior[prior]["records"] += records
            per_prior[prior]["time"] += float((out / "wall_s.txt").read_text())
            if prior == Sift.name:  # the peer: the PnP pose alone, where PnP found one
                peer = per_prior.setdefault("sift-pnp", {"records": [], "time": 0.0})
                peer["records"] += [pnp_only(r) for r in records]
                peer["time"] += sum(r.get("timings", {}).get("prior", 0.0) for r in records)
    return per_prior, gt


def main(args: argparse.Namespace) -> int:
    fconf = FeatureConfig(model=DEFAULT_MODEL, resize=512, image_scales=(1,), dtype="float16")
    lconf = LocalizerConfig(num_dbs=3, num_iters=50)
    rows: List[Dict] = []
    for key, parts in _sources(args, fconf):
        per_prior, gt = localize_priors(parts, args.priors, args.work / "search-runs", lconf,
                                        GlobalDescriptors(k=5, same_tag="area" if key == "demo" else None))
        for prior, v in per_prior.items():
            s = evaluate(v["records"], gt, THRESHOLDS)["all"]
            rows.append({"scene": key, "prior": prior, "n": s["refined"]["count"],
                         "prior_t": s["prior"]["median_t"], "prior_R": s["prior"]["median_R"],
                         **{k: s["refined"][k] for k in s["refined"] if k.startswith("recall@")},
                         "s_per_query": v["time"] / max(len(v["records"]), 1)})
    print(table(rows))
    return 0


def pnp_only(record: Dict) -> Dict:
    """A sift record as the SIFT + PnP peer reports it: its PnP pose (the record's prior) where PnP
    found one, else no pose."""
    return dict(record, success=False, prior=record["prior"] if pnp_pose_found(record.get("notes", [])) else None)


def table(rows: List[Dict]) -> str:
    keys = [k for k in rows[0] if k.startswith("recall@")]
    lines = ["| scene | prior | queries | its start: median t, R | " + " | ".join(k[len("recall@"):] for k in keys)
             + " | s / query | x top1 |", "| --- | --- | ---: | --- | " + " | ".join("---:" for _ in keys)
             + " | ---: | ---: |"]
    top1 = {r["scene"]: r["s_per_query"] for r in rows if r["prior"] == Top1.name}
    for r in rows:
        ratio = r["s_per_query"] / top1[r["scene"]] if top1.get(r["scene"]) and r["s_per_query"] else None
        lines.append(f"| {r['scene']} | {r['prior']} | {r['n']} | {fmt(r['prior_t'], '.2f')} m, "
                     f"{fmt(r['prior_R'], '.1f')} deg | "
                     + " | ".join(f"{fmt(100 * r[k] if r[k] is not None else None, '.0f')} %" for k in keys)
                     + f" | {fmt(r['s_per_query'], '.2f')} | {fmt(ratio, '.2f')} |")
    return "\n".join(lines)

