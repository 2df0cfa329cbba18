"""kapture datasets (sensors, rigs, trajectories, camera records), read without the kapture package.

Conventions (kapture 1.1): trajectories hold device_from_world poses
``qw qx qy qz tx ty tz``; rigs.txt holds each sensor's pose in its rig,
``sensor_from_rig``, so that sensor_from_world = sensor_from_rig @ rig_from_world.
"""

import csv
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

from pipeline.scene import CameraRecord, ImageRecord, SceneError, qvec_to_rotmat


def _rows(path: Path, min_fields: int, what: str) -> List[Tuple[str, List[str]]]:
    """(``file:line``, fields) of the data rows of a kapture CSV file (none if it is absent); a row
    with fewer than ``min_fields`` fields, or a file that is not text, is a SceneError there."""
    if not path.is_file():
        return []
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:  # -sig: a byte-order mark is not data
            rows = [(f"{path}:{k}", [c.strip() for c in row]) for k, row in enumerate(csv.reader(f), 1)
                    if row and row[0].strip() and not row[0].lstrip().startswith("#")]
    except (UnicodeDecodeError, csv.Error) as e:
        raise SceneError(f"{path}: not a kapture CSV file ({e})") from None
    for where, row in rows:
        if len(row) < min_fields:
            raise SceneError(f"{where}: expected {what}, got {len(row)} fields")
    return rows


def _once(seen: Dict, key, where: str, what: str) -> None:
    """Record that ``key`` is defined at ``where``; a second definition is a SceneError naming both
    (a dict would keep the last one silently)."""
    if key in seen:
        raise SceneError(f"{where}: {what} is defined twice (first at {seen[key]}): each once")
    seen[key] = where


def _parse(where: str, convert, what: str):
    """``convert()``, or a SceneError at ``where`` saying which value did not parse."""
    try:
        return convert()
    except (ValueError, TypeError, IndexError) as e:
        raise SceneError(f"{where}: bad {what}: {e}") from None


def _pose(values) -> np.ndarray:
    """device_from_world (3, 4); NaN where the quaternion is zero or not finite (the image is then
    refused, with its reason, where it is checked)."""
    qw, qx, qy, qz, tx, ty, tz = (float(v) for v in values[:7])
    q = np.array([qw, qx, qy, qz])
    if not np.isfinite(q).all() or np.linalg.norm(q) == 0:
        return np.full((3, 4), np.nan)
    return np.concatenate([qvec_to_rotmat(q), [[float(tx)], [float(ty)], [float(tz)]]], 1)


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """c_from_a = a (c_from_b) @ b (b_from_a), on 3x4 matrices."""
    return np.concatenate([a[:, :3] @ b[:, :3], (a[:, :3] @ b[:, 3] + a[:, 3])[:, None]], 1)


def read_kapture(root, tags=None) -> List[ImageRecord]:
    """Posed camera images of a kapture folder (the one holding ``sensors/``).

    Image names are paths relative to ``sensors/records_data``. Images
    without a pose (neither their own trajectory nor a rig's) are an error.
    """
    sensors_dir = Path(root) / "sensors"
    if not (sensors_dir / "sensors.txt").is_file():
        raise SceneError(f"{sensors_dir / 'sensors.txt'} not found: not a kapture dataset.")
    cameras: Dict[str, CameraRecord] = {}
    seen: Dict = {}
    for where, (sensor_id, _, kind, *params) in _rows(sensors_dir / "sensors.txt", 3, "sensor_id, name, type, ..."):
        _once(seen, ("sensor", sensor_id), where, f"sensor {sensor_id!r}")
        if kind == "camera":
            cameras[sensor_id] = _parse(where, lambda: CameraRecord(
                params[0], int(params[1]), int(params[2]), tuple(float(v) for v in params[3:])), "camera")
    rigs: Dict[str, Dict[str, np.ndarray]] = {}
    for where, (rig_id, sensor_id, *pose) in _rows(sensors_dir / "rigs.txt", 9, "rig_id, sensor_id, qw..tz"):
        _once(seen, ("rig", rig_id, sensor_id), where, f"sensor {sensor_id!r} of rig {rig_id!r}")
        rigs.setdefault(rig_id, {})[sensor_id] = _parse(where, lambda: _pose(pose), "pose")
    trajectories: Dict[Tuple[str, str], np.ndarray] = {}
    for where, (ts, dev, *pose) in _rows(sensors_dir / "trajectories.txt", 9, "timestamp, device_id, qw..tz"):
        _once(seen, ("pose", ts, dev), where, f"the pose of {dev!r} at timestamp {ts}")
        trajectories[(ts, dev)] = _parse(where, lambda: _pose(pose), "pose")
    images = []
    for where, row in _rows(sensors_dir / "records_camera.txt", 3, "timestamp, device_id, image_path"):
        ts, sensor_id, rel_path = row[:3]
        if sensor_id not in cameras:
            raise SceneError(f"{where}: record {rel_path} uses camera {sensor_id!r}, which "
                             f"{sensors_dir / 'sensors.txt'} does not define.")
        pose = trajectories.get((ts, sensor_id))
        rig_id = None
        if pose is None:
            for rig_id, members in rigs.items():
                if sensor_id in members and (ts, rig_id) in trajectories:
                    pose = _compose(members[sensor_id], trajectories[(ts, rig_id)])
                    break
        if pose is None:
            raise SceneError(f"{where}: image {rel_path} (timestamp {ts}, camera {sensor_id}) has no pose in "
                             f"{sensors_dir / 'trajectories.txt'} (nor through {sensors_dir / 'rigs.txt'}).")
        image_tags = {"camera": sensor_id, "timestamp": ts, **({"rig": rig_id} if rig_id else {}),
                      **dict(tags or {})}
        images.append(ImageRecord(rel_path, sensors_dir / "records_data" / rel_path, cameras[sensor_id],
                                  pose, image_tags, origin=where))
    if not images:
        raise SceneError(f"No camera records in {sensors_dir / 'records_camera.txt'}.")
    return images
