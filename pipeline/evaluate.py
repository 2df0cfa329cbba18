"""Accuracy against ground truth: pose errors, medians and recall per condition tag.

Queries whose ground truth is missing or not finite are not evaluated: they are counted
(``no_ground_truth``) and named in a warning, never turned into NaN medians. A query
without any pose (no record, or no prior) counts as an infinite error in the recalls and is
counted (``no_pose``); medians are over the queries that have a pose. Summaries hold no NaN or
infinity (``None`` where a value is undefined), so that they are valid JSON.
"""

import json
import logging
import math
from collections import defaultdict
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from pixloc.geometry import Pose, pose_error


logger = logging.getLogger(__name__)
DEFAULT_THRESHOLDS = ((0.25, 2.0), (0.5, 5.0), (5.0, 10.0))  # (metres, degrees), visuallocalization.net
INDOOR_THRESHOLDS = ((0.05, 5.0),)  # 7-Scenes, Cambridge


def parse_thresholds(values: Sequence[str]) -> Tuple[Tuple[float, float], ...]:
    """``["0.05,1", "0.25,2"]`` -> ((0.05, 1.0), (0.25, 2.0)): (scene units, degrees) pairs."""
    out = []
    for v in values:
        parts = v.split(",")
        try:
            t, r = (float(p) for p in parts)
        except ValueError:
            raise ValueError(f"Threshold {v!r}: write DISTANCE,DEGREES, e.g. 0.25,2.") from None
        if not (t > 0 and r > 0):
            raise ValueError(f"Threshold {v!r}: both values must be positive.")
        out.append((t, r))
    return tuple(out)


def pose_errors(T: Optional[np.ndarray], T_gt: np.ndarray) -> Tuple[float, float]:
    """Camera-centre distance (scene units) and rotation angle (degrees) between cam_from_world poses.

    A missing pose counts as an infinite error."""
    if T is None:
        return float("inf"), float("inf")
    dR, dt = pose_error(Pose.from_matrix(T), Pose.from_matrix(T_gt))
    return float(dt), float(dR)


def record_errors(rec: Optional[Dict], T_gt: np.ndarray) -> Dict[str, Tuple[float, float]]:
    """(t, R) errors of a record against ground truth: ``result`` (the reported pose: refined where
    verified, else the prior), ``refined`` (the refinement, verified or not) and ``prior``; inf
    where there is no such pose (no record, a failure)."""
    from pipeline.localization.results import record_pose

    def err(T):
        return pose_errors(None if T is None else np.asarray(T, np.float64), T_gt)
    if rec is None:
        return {"result": err(None), "refined": err(None), "prior": err(None)}
    return {"result": err(record_pose(rec)), "refined": err(rec.get("refined")), "prior": err(rec.get("prior"))}


def _median(x: np.ndarray) -> Optional[float]:
    return float(np.median(x)) if len(x) else None


def recall_label(key: str, units: str = "m") -> str:
    """'0.25 m, 2 deg' for the summary key 'recall@0.25m,2deg' (keys keep 'm' whatever the map's
    units: ``units`` is what the distance is in, e.g. 'SfM units')."""
    t, r = key[len("recall@"):].split(",")
    return f"{float(t.removesuffix('m')):.3g} {units}, {float(r.removesuffix('deg')):g} deg"


def summarize(errors: Sequence[Tuple[float, float]], thresholds=DEFAULT_THRESHOLDS) -> Dict:
    """Median errors over the queries with a pose, and recall (fraction of all queries within each
    (distance, degrees) pair; a query without a pose is never within). None where undefined."""
    e = np.asarray(errors, np.float64).reshape(-1, 2)
    posed = e[np.isfinite(e).all(1)]
    out = {"count": int(len(e)), "no_pose": int(len(e) - len(posed)),
           "median_t": _median(posed[:, 0]), "median_R": _median(posed[:, 1])}
    for t, r in thresholds:
        out[f"recall@{t}m,{r}deg"] = float(np.mean((e[:, 0] <= t) & (e[:, 1] <= r))) if len(e) else None
    return out


def usable_ground_truth(ground_truth: Dict[str, Optional[np.ndarray]]) -> Tuple[Dict[str, np.ndarray], List[str]]:
    """The finite (3, 4) ground-truth poses, and the names of queries without one."""
    good, missing = {}, []
    for name, T in ground_truth.items():
        T = None if T is None else np.asarray(T, np.float64)
        if T is None or T.shape != (3, 4) or not np.isfinite(T).all():
            missing.append(name)
        else:
            good[name] = T
    return good, missing


def evaluate(records: List[Dict], ground_truth: Dict[str, Optional[np.ndarray]], thresholds=DEFAULT_THRESHOLDS,
             tag_keys: Optional[Sequence[str]] = None) -> Dict[str, Dict]:
    """Summaries of refined and prior poses: overall (``all``) and per ``key=value`` condition tag.

    ``ground_truth`` may name queries without a usable pose (None, NaN): they are excluded,
    counted in ``no_ground_truth`` of ``all`` and logged. Queries in ``ground_truth`` without a
    record count as queries without a pose.
    """
    gt, missing = usable_ground_truth(ground_truth)
    if missing:
        logger.warning("%d queries have no ground truth and are not evaluated: %s%s", len(missing),
                       ", ".join(missing[:5]), " ..." if len(missing) > 5 else "")
    by_name = {r["name"]: r for r in records}
    groups: Dict[str, Dict[str, List]] = defaultdict(lambda: {"refined": [], "prior": []})
    groups["all"]  # always present, first
    for name, T_gt in gt.items():
        rec = by_name.get(name)
        e = record_errors(rec, T_gt)
        refined, prior = e["result"], e["prior"]
        tags = rec.get("tags", {}) if rec else {}
        keys = ["all"] + [f"{k}={v}" for k, v in sorted(tags.items()) if tag_keys is None or k in tag_keys]
        for key in keys:
            groups[key]["refined"].append(refined)
            groups[key]["prior"].append(prior)
    out = {key: {"refined": summarize(g["refined"], thresholds), "prior": summarize(g["prior"], thresholds),
                 "errors": g["refined"], "prior_errors": g["prior"]} for key, g in groups.items()}
    out["all"]["no_ground_truth"] = len(missing)
    return out


def shown_families(summary: Dict, group_by: Optional[Sequence[str]] = None) -> Dict[str, List[str]]:
    """{family: its ``family=value`` keys} worth a table: with ``group_by``, those families;
    otherwise every family but those with one value for every query (the same as ``all``) and
    those whose every value is a single query (a camera id or a timestamp per query: a table of
    one-query rows and plots of one point say nothing)."""
    families: Dict[str, List[str]] = {}
    for key in summary:
        if key != "all" and "=" in key:
            families.setdefault(key.split("=", 1)[0], []).append(key)
    if group_by is not None:
        unknown = [f for f in group_by if f not in families]
        if unknown:  # a typo would otherwise leave its table out without a word
            raise ValueError(f"--group-by: {', '.join(unknown)} {'is' if len(unknown) == 1 else 'are'} not a tag of "
                             f"these queries (theirs: {', '.join(sorted(families)) or 'none'}).")
        return {f: keys for f, keys in families.items() if f in group_by}
    return {f: keys for f, keys in families.items()
            if len(keys) > 1 and not all(summary[k]["refined"]["count"] <= 1 for k in keys)}


def evaluation_document(summary: Dict, records: List[Dict], ground_truth: Dict, thresholds) -> Dict:
    """What ``evaluation.json`` holds (schema in docs/evaluation.md, version 2):

    ``thresholds``: [[distance, degrees], ...]; ``no_ground_truth``: how many queries were not
    evaluated; ``queries``: per query with ground truth, ``{name, outcome, tags, result: {t, R},
    prior: {t, R}}`` (errors in scene units and degrees; null where there is no pose);
    ``conditions``: per ``all`` and ``key=value`` tag, ``{result: {...}, prior: {...}}`` with
    ``count``, ``median_t``, ``median_R`` and ``recall@{t}m,{R}deg`` (fractions of all its
    queries). ``result`` is the reported pose: refined where verification accepted it, else the prior.
    """
    from pipeline.localization.results import outcome

    gt, _ = usable_ground_truth(ground_truth)
    by_name = {r["name"]: r for r in records}
    queries = []
    for name, T_gt in gt.items():
        rec = by_name.get(name)
        e = record_errors(rec, T_gt)  # inf where there is no pose: null in the JSON (to_json)
        queries.append({"name": name, "outcome": outcome(rec) if rec else "missing",
                        "tags": (rec or {}).get("tags", {}), **{k: dict(zip("tR", e[k])) for k in ("result", "prior")}})
    return {"version": 2, "thresholds": [list(t) for t in thresholds],
            "no_ground_truth": summary["all"].get("no_ground_truth", 0), "queries": queries,
            "conditions": {key: {"result": s["refined"], "prior": s["prior"]} for key, s in summary.items()}}


def to_json(summary) -> str:
    """JSON without NaN or infinity: those become null (strict JSON readers refuse them)."""
    def clean(x):
        if isinstance(x, float):
            return x if math.isfinite(x) else None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x
    return json.dumps(clean(summary), indent=1, allow_nan=False)


def fmt(value: Optional[float], spec: str, none: str = "-") -> str:
    """``format(value, spec)``, or ``none`` for an undefined value (never 'nan')."""
    return none if value is None or not math.isfinite(value) else format(value, spec)
