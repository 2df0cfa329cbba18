"""``pixloc evaluate-model``: feature models compared on held-out image pairs, with the same
initial poses for every model.

The held-out sources come from the training config (``held_out``; by default
strecha/Herz-Jesus-P8 and 7scenes_stairs, never used in training). Each pair (reference,
query) is aligned from coarse to fine starting from an initial pose a seeded fraction of the
way from the reference pose to the truth (the training sampling); the query's pose error is
then measured in metres and degrees. Writes ``model_eval.json`` and ``model_eval.md``.
"""

import argparse
import json
import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import torch

from pipeline.evaluate import fmt, summarize
from pipeline.scene import CameraRecord
from pipeline.training_data import PairDataset
from pixloc.geometry import pose_error
from pixloc.nets.registry import load_refiner

from .train import default_data_root, load_config, load_sources, pair_config

logger = logging.getLogger(__name__)
THRESHOLDS = ((0.05, 2.0), (0.25, 2.0))


def evaluate_models(models: Sequence[str], datasets: Sequence[Tuple[str, PairDataset]], max_pairs: int,
                    num_iters: int = 100, seed: int = 0) -> Dict[str, Dict[str, Dict[str, float]]]:
    """{model: {dataset or 'all' or 'prior': summary}}: pose errors after alignment of the same
    seeded pairs and initial poses for every model."""
    pairs = {name: ds.fixed(max_pairs, seed) for name, ds in datasets}
    results: Dict[str, Dict[str, Dict[str, float]]] = {}

    def errors(T_est, batch) -> Tuple[float, float]:
        dR, dt = pose_error(T_est.double(), batch.query_from_ref_gt.double())
        return float(dt[0]), float(dR[0])

    def summaries(per: Dict[str, List[Tuple[float, float]]]) -> Dict[str, Dict[str, float]]:
        out = {name: summarize(e, THRESHOLDS) for name, e in per.items()}
        out["all"] = summarize([x for e in per.values() for x in e], THRESHOLDS)
        return out

    results["prior"] = summaries({name: [errors(b.query_from_ref_init, b) for b in ps] for name, ps in pairs.items()})
    for model in models:
        refiner = load_refiner(model).eval()
        for s in refiner.solvers:
            s.num_iters = num_iters
        per, t0 = {}, time.perf_counter()
        with torch.no_grad():
            for name, ps in pairs.items():
                per[name] = [errors(refiner(b)["query_from_ref"][-1], b) for b in ps]
        results[model] = summaries(per)
        results[model]["all"]["seconds_per_pair"] = (time.perf_counter() - t0) / sum(map(len, pairs.values()))
        logger.info("%s: %s", model, results[model]["all"])
    return results


def markdown(results: Dict[str, Dict[str, Dict[str, float]]]) -> str:
    keys = [k for k in next(iter(results.values()))["all"] if k.startswith("recall@")]
    lines = ["| model | data | pairs | median t (cm) | median R (deg) | " + " | ".join(keys) + " |",
        "| --- | --- | ---: | ---: | ---: | " + " | ".join("---:" for _ in keys) + " |"]
    for model, per in results.items():
        for data, s in per.items():
            lines.append(f"| {model} | {data} | {s['count']} | {fmt(100 * s['median_t'] if s['median_t'] is not None else None, '.1f')} | "
                         f"{fmt(s['median_R'], '.2f')} | "
                         + " | ".join(fmt(s[k], ".3f") for k in keys) + " |")
    return "\n".join(lines) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", nargs="+", default=["pixloc-lite0", "lite0-imagenet", "photometric"],
                   help="model names or files (default: the shipped model, its initialisation, raw RGB)")
    p.add_argument("--config", default="lite0", help="training config whose held_out sources to use")
    p.add_argument("--data-root", type=Path, help="default $PIXLOC_SHARED/data or ../shared/data")
    p.add_argument("--output", type=Path, default=Path("outputs/model_eval"))
    p.add_argument("--max-pairs", type=int, default=40, help="pairs per held-out source (seeded choice)")
    p.add_argument("--max-size", type=int, help="longer image side (default: the config's)")
    p.add_argument("--iters", type=int, default=100, help="LM iterations per level")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--init-range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="initial poses this fraction of the way from the reference pose to the truth "
                        "(default: the config's init_range, [0.75, 1]; e.g. 0.25 0.5 for far starts)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    held_out: List[Dict] = config.get("held_out_sources") or []
    if not held_out:
        raise ValueError(f"Config {args.config!r} names no held-out sources (held_out_sources).")
    data_root = args.data_root or default_data_root()
    m, w, h, params = config.get("synthetic_camera", ["PINHOLE", 320, 240, [250.0, 250.0, 160.0, 120.0]])
    sources, skipped = load_sources(held_out, data_root, args.output / "data", CameraRecord(m, w, h, tuple(params)))
    if skipped:
        raise ValueError(f"Held-out data missing under {data_root}: {', '.join(skipped)}.")
    pconf = replace(pair_config(config), far_init_prob=0.0,  # every pair from the one range evaluated
                    max_size=args.max_size or int(config.get("max_size", 320)),
                    init_range=tuple(args.init_range or config.get("init_range", (0.75, 1.0))))
    datasets = [(s.name, s.dataset(pconf)) for s in sources]
    results = evaluate_models(args.models, datasets, args.max_pairs, args.iters, args.seed)
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "model_eval.json").write_text(json.dumps(results, indent=1))
    table = markdown(results)
    (args.output / "model_eval.md").write_text(table)
    print(table)
    return 0
