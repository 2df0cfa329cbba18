"""Localization outputs: poses in the visuallocalization.net format and one JSON record per query."""

import json
from pathlib import Path
from typing import Dict, Iterable, List, Optional

import numpy as np

from .localize import QueryResult
from .scene import rotmat_to_qvec


REJECTED = "rejected: "  # reason prefix of refinements that verification did not accept


def outcome(rec: Dict) -> str:
    """``refined`` (verified), ``rejected`` (refined, but the evidence did not support it: the prior
    is reported) or ``failed`` (no refinement: bad input, too few points, LM failure)."""
    if rec["success"]:
        return "refined"
    return "rejected" if rec.get("reason", "").startswith(REJECTED) else "failed"


def is_retryable(rec: Optional[Dict]) -> bool:
    """Whether a rerun should redo this query: a failure whose cause may have been fixed since
    (unreadable image, bad query line, store or job problem), not an outcome of the method on
    good input (a rejected refinement, too few points, an LM failure)."""
    if rec is None:
        return True
    if rec["success"] or outcome(rec) == "rejected":
        return False
    reason = rec.get("reason", "")
    return not (reason.startswith("LM failed") or reason.startswith("references see"))


def result_to_record(r: QueryResult, tags: Optional[Dict[str, str]] = None) -> Dict:
    def mat(T):
        return None if T is None else np.asarray(T, np.float64).tolist()
    return {"name": r.name, "success": r.success, "prior": mat(r.prior), "refined": mat(r.refined),
            "references": r.references, "num_points": r.num_points,
            "cost": None if not np.isfinite(r.cost) else r.cost, "iterations": r.iterations,
            "reason": r.reason, "confidence": r.confidence, "evidence": r.evidence, "notes": r.notes, "filters": r.filters, "timings": r.timings,
            "tags": dict(tags or {}), "per_level": r.per_level}


def write_records(records: Iterable[Dict], path) -> None:
    """JSON lines, written to a temporary file then renamed: a record file is complete or absent."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w") as f:
        for rec in records:
            f.write(json.dumps(rec) + "\n")
    tmp.replace(path)


def read_records(path) -> List[Dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def record_pose(rec: Dict) -> Optional[np.ndarray]:
    """The reported pose: refined if successful, else the prior (official PixLoc)."""
    T = rec["refined"] if rec["success"] else rec["prior"]
    return None if T is None else np.asarray(T, np.float64)


def write_failed(records: Iterable[Dict], path) -> int:
    """``name<TAB>outcome<TAB>reason`` per query without a verified pose (their line in poses.txt,
    if any, is the prior); returns the count."""
    lines = [f"{r['name']}\t{outcome(r)}\t{r['reason']}" for r in records if not r["success"]]
    Path(path).write_text("".join(line + "\n" for line in lines))
    return len(lines)


def write_poses(records: Iterable[Dict], path, prepend_camera: Optional[bool] = None) -> int:
    """``name qw qx qy qz tx ty tz`` (cam_from_world) per query with a pose; returns the count.

    prepend_camera: write ``parentdir/basename`` names (RobotCar, 7-Scenes, Cambridge);
    by default only when basenames alone would be ambiguous.
    """
    records = list(records)
    if prepend_camera is None:
        basenames = [Path(r["name"]).name for r in records]
        prepend_camera = len(set(basenames)) < len(basenames)
    lines = []
    for rec in records:
        T = record_pose(rec)
        if T is None:
            continue
        name = Path(rec["name"])
        name = f"{name.parent.name}/{name.name}" if prepend_camera else name.name
        q = rotmat_to_qvec(T[:, :3])
        lines.append(" ".join([name, *(f"{v:.10g}" for v in q), *(f"{v:.10g}" for v in T[:, 3])]))
    Path(path).write_text("\n".join(lines) + ("\n" if lines else ""))
    return len(lines)
