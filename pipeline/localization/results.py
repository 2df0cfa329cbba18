"""Localization outputs: poses in the visuallocalization.net format and one JSON record per query."""

import json
import re
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Tuple

import numpy as np

from pipeline.localization.refine import QueryResult
from pipeline.scene import CameraRecord, rotmat_to_qvec
from pipeline.textfiles import read_json_lines, write_atomic


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
    rec = {"name": r.name, "success": r.success, "prior": mat(r.prior), "refined": mat(r.refined),
           "references": r.references, "num_points": r.num_points,
           "cost": None if not np.isfinite(r.cost) else r.cost, "iterations": r.iterations,
           "reason": r.reason, "confidence": r.confidence, "evidence": r.evidence, "notes": r.notes,
           "filters": r.filters, "timings": r.timings,
           "tags": dict(tags or {}), "per_level": r.per_level}
    if r.body:  # an image of a rig frame: the frame's key, pose and verdict (``pipeline.localization.rigs``)
        rec["body"] = r.body
    return rec


def write_records(records: Iterable[Dict], path) -> None:
    """JSON lines, written atomically: a record file is complete or absent."""
    write_atomic(path, "".join(json.dumps(rec) + "\n" for rec in records))


def read_records(path) -> List[Dict]:
    """The records of a JSON-lines file; a damaged line is an InputError with ``file:line``."""
    return read_json_lines(path, "records file")


def record_pose(rec: Dict) -> Optional[np.ndarray]:
    """The reported pose: refined if successful, else the prior (official PixLoc)."""
    T = rec["refined"] if rec["success"] else rec["prior"]
    return None if T is None else np.asarray(T, np.float64)


def stages_text(rec: Dict) -> str:
    """What each stage before the refinement did, as its notes say (e.g. the SIFT prior's PnP
    inliers, or that the search took over): where a failure began."""
    return " | ".join(rec.get("notes") or [])


def write_failed(records: Iterable[Dict], path) -> int:
    """``name<TAB>outcome<TAB>reason<TAB>stages`` per query without a verified pose (their line in
    poses.txt, if any, is the prior; stages: ``stages_text``); returns the count."""
    lines = [f"{r['name']}\t{outcome(r)}\t{r['reason']}\t{stages_text(r)}" for r in records if not r["success"]]
    write_atomic(path, "".join(line + "\n" for line in lines))
    return len(lines)


POSE_NAMES = ("full", "basename", "camera")


def pose_name(name: str, names: str = "full") -> str:
    """A query's name in a poses file: ``full`` (as the query list has it, relative to the
    image folder), ``basename`` (Aachen, CMU submissions) or ``camera`` (``parentdir/basename``:
    RobotCar, 7-Scenes, Cambridge)."""
    path = Path(name)
    camera = f"{path.parent.name}/{path.name}" if path.parent.name else path.name  # never '/a.jpg'
    return {"full": name, "basename": path.name, "camera": camera}[names]


def pose_names_problem(names: List[str], how: str) -> Optional[str]:
    """Why ``how`` cannot name these queries in a poses file (unknown, or it makes two alike), or None."""
    if how not in POSE_NAMES:
        return f"pose names {how!r}: choose one of {', '.join(POSE_NAMES)}"
    written = [pose_name(n, how) for n in names]
    if len(set(written)) < len(written):
        dup = sorted({n for n in written if written.count(n) > 1})
        other = [h for h in POSE_NAMES if h != how and len({pose_name(n, h) for n in names}) == len(names)]
        return f"--pose-names {how} makes query names alike ({', '.join(dup[:3])}): use {' or '.join(other)}"
    return None


def write_poses(records: Iterable[Dict], path, names: str = "full") -> int:
    """``name qw qx qy qz tx ty tz`` (cam_from_world) per query with a pose; returns the count.
    ``names``: see ``pose_name``; names that it would make alike are refused (ValueError)."""
    records = list(records)
    problem = pose_names_problem([r["name"] for r in records], names)
    if problem:
        raise ValueError(problem)
    written = [pose_name(r["name"], names) for r in records]
    lines = []
    for rec, name in zip(records, written):
        T = record_pose(rec)
        if T is None:
            continue
        q = rotmat_to_qvec(T[:, :3])
        lines.append(" ".join([name, *(f"{v:.10g}" for v in q), *(f"{v:.10g}" for v in T[:, 3])]))
    write_atomic(path, "\n".join(lines) + ("\n" if lines else ""))
    return len(lines)


KAPTURE_HEADER = "# kapture format: 1.1\n"


def write_kapture(records: Iterable[Dict], cameras: Dict[str, CameraRecord], folder) -> int:
    """The reported poses as a kapture folder (``sensors/``: sensors.txt, records_camera.txt,
    trajectories.txt with device_from_world poses), readable by kapture tools; returns the
    number of poses. Queries read from kapture keep their timestamp and camera id (tags
    ``timestamp``, ``camera``); others get their index and one camera id per distinct camera.
    ``cameras``: query name -> CameraRecord. The images themselves are not copied."""
    sensors = Path(folder) / "sensors"
    sensors.mkdir(parents=True, exist_ok=True)
    ids: Dict[tuple, str] = {}
    sensor_rows, record_rows, trajectory_rows = [], [], []
    for k, rec in enumerate(records):
        cam = cameras[rec["name"]]
        key = (cam.model, cam.width, cam.height, tuple(cam.params))
        sensor = rec.get("tags", {}).get("camera") or ids.get(key) or f"query_cam{len(ids)}"
        if sensor not in ids.values():
            ids[key] = sensor
            sensor_rows.append(", ".join([sensor, "", "camera", cam.model, str(cam.width), str(cam.height),
                                          *(f"{p:.10g}" for p in cam.params)]))
        ts = str(rec.get("tags", {}).get("timestamp", k))
        record_rows.append(f"{ts}, {sensor}, {rec['name']}")
        T = record_pose(rec)
        if T is not None:
            q = rotmat_to_qvec(T[:, :3])
            trajectory_rows.append(", ".join([ts, sensor, *(f"{v:.10g}" for v in q), *(f"{v:.10g}" for v in T[:, 3])]))
    for name, head, rows in (("sensors.txt", "# sensor_id, name, sensor_type, [sensor_params]+", sensor_rows),
                             ("records_camera.txt", "# timestamp, device_id, image_path", record_rows),
                             ("trajectories.txt", "# timestamp, device_id, qw, qx, qy, qz, tx, ty, tz",
                              trajectory_rows)):
        write_atomic(sensors / name, KAPTURE_HEADER + head + "\n" + "".join(r + "\n" for r in rows))
    return len(trajectory_rows)


def reason_kind(reason: str) -> str:
    """A failure reason with its figures and details left out, so that reasons that differ only
    in those count as one kind ('references see 3 points (< 10)' -> 'references see # points')."""
    return re.sub(r"\d+(\.\d+)?", "#", reason.split(" (")[0]).strip()


def reason_groups(records: Iterable[Dict]) -> List[Tuple[str, str, List[Dict]]]:
    """(outcome, kind, records) of the queries without a verified pose, largest group first."""
    groups: Dict[Tuple[str, str], List[Dict]] = {}
    for r in records:
        if not r["success"]:
            groups.setdefault((outcome(r), reason_kind(r["reason"])), []).append(r)
    return sorted(((o, k, v) for (o, k), v in groups.items()), key=lambda g: (-len(g[2]), g[0], g[1]))
