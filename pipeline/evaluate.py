"""Accuracy against ground truth: pose errors, medians and recall per condition tag."""

from collections import defaultdict
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from pixloc.geometry import pose_error

from .scene import pose_from_matrix

DEFAULT_THRESHOLDS = ((0.25, 2.0), (0.5, 5.0), (5.0, 10.0))  # (metres, degrees), visuallocalization.net
INDOOR_THRESHOLDS = ((0.05, 5.0),)  # 7-Scenes, Cambridge


def pose_errors(T: Optional[np.ndarray], T_gt: np.ndarray) -> Tuple[float, float]:
    """Camera-centre distance (scene units) and rotation angle (degrees) between cam_from_world poses.

    A missing pose counts as an infinite error."""
    if T is None:
        return float("inf"), float("inf")
    dR, dt = pose_error(pose_from_matrix(T), pose_from_matrix(T_gt))
    return float(dt), float(dR)


def summarize(errors: Sequence[Tuple[float, float]], thresholds=DEFAULT_THRESHOLDS) -> Dict:
    """Median errors and recall (fraction of queries within each (metres, degrees) pair)."""
    e = np.asarray(errors, np.float64).reshape(-1, 2)
    out = {"count": int(len(e)),
           "median_t": float(np.median(e[:, 0])) if len(e) else float("nan"),
           "median_R": float(np.median(e[:, 1])) if len(e) else float("nan")}
    for t, r in thresholds:
        out[f"recall@{t}m,{r}deg"] = float(np.mean((e[:, 0] <= t) & (e[:, 1] <= r))) if len(e) else float("nan")
    return out


def evaluate(records: List[Dict], ground_truth: Dict[str, np.ndarray], thresholds=DEFAULT_THRESHOLDS,
             tag_keys: Optional[Sequence[str]] = None) -> Dict[str, Dict]:
    """Summaries of refined and prior poses: overall (``all``) and per ``key=value`` condition tag.

    Queries in ``ground_truth`` without a record count as failures (infinite error).
    """
    from .results import record_pose

    by_name = {r["name"]: r for r in records}
    groups: Dict[str, Dict[str, List]] = defaultdict(lambda: {"refined": [], "prior": []})
    for name, T_gt in ground_truth.items():
        rec = by_name.get(name)
        refined = pose_errors(record_pose(rec) if rec else None, T_gt)
        prior = pose_errors(np.asarray(rec["prior"]) if rec and rec["prior"] is not None else None, T_gt)
        tags = rec.get("tags", {}) if rec else {}
        keys = ["all"] + [f"{k}={v}" for k, v in sorted(tags.items()) if tag_keys is None or k in tag_keys]
        for key in keys:
            groups[key]["refined"].append(refined)
            groups[key]["prior"].append(prior)
    return {key: {"refined": summarize(g["refined"], thresholds), "prior": summarize(g["prior"], thresholds),
                  "errors": g["refined"], "prior_errors": g["prior"]} for key, g in groups.items()}
