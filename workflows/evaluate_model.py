"""``pixloc evaluate-model``: feature models compared on held-out image pairs, with the same
initial poses for every model.

The held-out sources come from the training config (``held_out``; by default
strecha/Herz-Jesus-P8 and 7scenes_stairs, never used in training). Each pair (reference,
query) is aligned from coarse to fine starting from an initial pose a seeded fraction of the
way from the reference pose to the truth (the training sampling); the query's pose error is
then measured in metres and degrees. Writes ``model_eval.json`` and ``model_eval.md``.

Medians and recalls of a few dozen pairs move by a pair or two between close models. So each
model after the first is also compared with the first pair by pair (``paired``): on how many pairs
it ends closer or farther, the pairs it brings within each recall threshold or loses, and a sign
test of closer against farther. Per-pair errors go to ``model_eval_pairs.json``. Rerunning into
the same ``--output`` reuses its triangulations, so that models run at different times meet the
same pairs.
"""

import argparse
import json
import logging
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import torch

from pipeline.evaluate import fmt, summarize
from pipeline.data.training_data import PairDataset
from pixloc.geometry import pose_error
from pixloc.nets.registry import load_refiner

from .options import at_least
from .train import load_config
from .training_sources import default_data_root, load_sources

logger = logging.getLogger(__name__)
THRESHOLDS = ((0.05, 2.0), (0.25, 2.0))
TIE_M = 1e-3  # translation errors closer than this count as a tie in the paired comparison
Errors = Dict[str, Dict[str, List[Tuple[float, float]]]]  # model -> dataset -> (t m, R deg) per pair


def evaluate_models(models: Sequence[str], datasets: Sequence[Tuple[str, PairDataset]], max_pairs: int,
                    num_iters: int = 100, seed: int = 0, pair_errors: Optional[Errors] = None
                    ) -> Dict[str, Dict[str, Dict[str, float]]]:
    """{model: {dataset or 'all' or 'prior': summary}}: pose errors after alignment of the same
    seeded pairs and initial poses for every model; ``pair_errors``, if given, receives each
    pair's errors ({model or 'prior': {dataset: [(t, R)]}})."""
    pairs = {name: ds.fixed(max_pairs, seed) for name, ds in datasets}
    results: Dict[str, Dict[str, Dict[str, float]]] = {}

    def errors(T_est, batch) -> Tuple[float, float]:
        dR, dt = pose_error(T_est.double(), batch.query_from_ref_gt.double())
        return float(dt[0]), float(dR[0])

    def summaries(per: Dict[str, List[Tuple[float, float]]]) -> Dict[str, Dict[str, float]]:
        out = {name: summarize(e, THRESHOLDS) for name, e in per.items()}
        out["all"] = summarize([x for e in per.values() for x in e], THRESHOLDS)
        return out

    pair_errors = {} if pair_errors is None else pair_errors
    pair_errors["prior"] = {name: [errors(b.query_from_ref_init, b) for b in ps] for name, ps in pairs.items()}
    results["prior"] = summaries(pair_errors["prior"])
    for model in models:
        refiner = load_refiner(model).eval()
        per, t0 = {}, time.perf_counter()
        with torch.no_grad():
            for name, ps in pairs.items():
                per[name] = [errors(refiner(b, num_iters=num_iters)["query_from_ref"][-1], b) for b in ps]
        pair_errors[model] = per
        results[model] = summaries(per)
        results[model]["all"]["seconds_per_pair"] = (time.perf_counter() - t0) / sum(map(len, pairs.values()))
        logger.info("%s: %s", model, results[model]["all"])
    return results


def sign_test(wins: int, losses: int) -> float:
    """Two-sided p-value of ``wins`` against ``losses`` if either were equally likely (ties left out)."""
    n, k = wins + losses, min(wins, losses)
    if n == 0:
        return 1.0
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n)


def paired(pair_errors: Errors, baseline: str) -> Dict[str, Dict[str, Dict[str, float]]]:
    """{model: {dataset or 'all': comparison with ``baseline`` on the same pairs}}: pairs where the
    model ends closer / farther in translation (by more than ``TIE_M``), the sign test of the two,
    and per recall threshold the pairs it brings within (gained) or takes out (lost)."""
    def within(e, t, r):
        return e[0] <= t and e[1] <= r

    def compare(a: List[Tuple[float, float]], b: List[Tuple[float, float]]) -> Dict[str, float]:
        # a pair without a pose (NaN) counts as the worst error
        a, b = ([tuple(x if math.isfinite(x) else math.inf for x in e) for e in side] for side in (a, b))
        closer = sum(eb[0] < ea[0] - TIE_M for ea, eb in zip(a, b))
        farther = sum(eb[0] > ea[0] + TIE_M for ea, eb in zip(a, b))
        out = {"pairs": len(a), "closer": closer, "farther": farther, "sign_test_p": sign_test(closer, farther)}
        for t, r in THRESHOLDS:
            out[f"gained@{t}m,{r}deg"] = sum(within(eb, t, r) and not within(ea, t, r) for ea, eb in zip(a, b))
            out[f"lost@{t}m,{r}deg"] = sum(within(ea, t, r) and not within(eb, t, r) for ea, eb in zip(a, b))
        return out

    base = pair_errors[baseline]
    out = {}
    for model, per in pair_errors.items():
        if model in (baseline, "prior"):
            continue
        out[model] = {name: compare(base[name], e) for name, e in per.items()}
        out[model]["all"] = compare([x for n in per for x in base[n]], [x for e in per.values() for x in e])
    return out


def comparison_lines(columns: Sequence[str], keys: Sequence[str], rows) -> List[str]:
    """A Markdown table of paired comparisons: ``columns`` name the first three cells (e.g. model,
    data, pairs); each row is those three, closer, farther, the sign test's p and a (gained, lost)
    pair per threshold of ``keys``."""
    lines = ["| " + " | ".join(columns) + " | closer | farther | sign test p | "
             + " | ".join(f"gained / lost {k}" for k in keys) + " |",
             "| --- | --- | ---: | ---: | ---: | ---: | " + " | ".join("---:" for _ in keys) + " |"]
    for *first, closer, farther, p, changes in rows:
        lines.append("| " + " | ".join(str(x) for x in first) + f" | {closer} | {farther} | {p:.3f} | "
                     + " | ".join(f"{g} / {lost}" for g, lost in changes) + " |")
    return lines


def paired_markdown(comparison: Dict[str, Dict[str, Dict[str, float]]], baseline: str) -> str:
    if not comparison:
        return ""
    keys = [f"{t}m,{r}deg" for t, r in THRESHOLDS]
    rows = [(model, data, c["pairs"], c["closer"], c["farther"], c["sign_test_p"],
             [(c["gained@" + k], c["lost@" + k]) for k in keys])
            for model, per in comparison.items() for data, c in per.items()]
    return "\n".join([f"Pair by pair against {baseline} (same pairs; closer / farther: translation error, ties "
                      f"within {1000 * TIE_M:.0f} mm; gained / lost: pairs brought within or taken out of each "
                      "threshold):", ""] + comparison_lines(("model", "data", "pairs"), keys, rows)) + "\n"


def markdown(results: Dict[str, Dict[str, Dict[str, float]]]) -> str:
    keys = [k for k in next(iter(results.values()))["all"] if k.startswith("recall@")]
    lines = ["| model | data | pairs | median t (cm) | median R (deg) | " + " | ".join(keys) + " |",
        "| --- | --- | ---: | ---: | ---: | " + " | ".join("---:" for _ in keys) + " |"]
    for model, per in results.items():
        for data, s in per.items():
            median_cm = 100 * s["median_t"] if s["median_t"] is not None else None
            lines.append(f"| {model} | {data} | {s['count']} | {fmt(median_cm, '.1f')} | "
                         f"{fmt(s['median_R'], '.2f')} | "
                         + " | ".join(fmt(s[k], ".3f") for k in keys) + " |")
    return "\n".join(lines) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", nargs="+", default=["pixloc-lite0", "lite0-imagenet", "photometric"],
                   help="model names or files (default: the shipped model, its initialisation, raw RGB); the "
                        "others are compared pair by pair with the first")
    p.add_argument("--config", default="lite0", help="training config whose held_out sources to use")
    p.add_argument("--data-root", type=Path, help="default $PIXLOC_SHARED/data or ../shared/data")
    p.add_argument("--output", type=Path, default=Path("outputs/model_eval"),
                   help="folder of the tables, the per-pair errors and the reused triangulation")
    p.add_argument("--max-pairs", type=at_least(1), default=40, help="pairs per held-out source (seeded choice)")
    p.add_argument("--max-size", type=at_least(16), help="longer image side (default: the config's)")
    p.add_argument("--iters", type=at_least(1), default=100, help="LM iterations per level")
    p.add_argument("--threads", type=at_least(0), default=0,
                   help="torch threads (default: torch's choice; 1 beside another busy job, whose core the "
                        "threads would otherwise wait on)")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial poses (the same pairs for every model)")
    p.add_argument("--init-range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="initial poses this fraction of the way from the reference pose to the truth "
                        "(default: the config's init_range, [0.75, 1]; e.g. 0.25 0.5 for far starts)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    if args.threads:
        torch.set_num_threads(args.threads)
    run = load_config(args.config)
    held_out: List[Dict] = list(run.held_out_sources)
    if not held_out:
        raise ValueError(f"Config {args.config!r} names no held-out sources (held_out_sources).")
    data_root = args.data_root or default_data_root()
    sources, skipped = load_sources(held_out, data_root, args.output / "data", run.camera())
    if skipped:
        raise ValueError(f"Held-out data missing under {data_root}: {', '.join(skipped)}.")
    pconf = replace(run.pairs, far_init_prob=0.0,  # every pair from the one range evaluated
                    max_size=args.max_size or run.pairs.max_size,
                    init_range=tuple(args.init_range or run.pairs.init_range))
    datasets = [(s.name, s.dataset(pconf)) for s in sources]
    pair_errors: Errors = {}
    results = evaluate_models(args.models, datasets, args.max_pairs, args.iters, args.seed, pair_errors)
    comparison = paired(pair_errors, args.models[0])
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "model_eval.json").write_text(json.dumps(results, indent=1))
    (args.output / "model_eval_pairs.json").write_text(json.dumps(
        {"errors": pair_errors, "paired": {"baseline": args.models[0], "models": comparison}}, indent=1))
    table = markdown(results)
    if comparison:
        table += "\n" + paired_markdown(comparison, args.models[0])
    (args.output / "model_eval.md").write_text(table)
    print(table)
    return 0
