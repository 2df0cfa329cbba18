"""kapture datasets (sensors, rigs, trajectories, camera records), read without the kapture package.

Conventions (kapture 1.1): trajectories hold device_from_world poses
``qw qx qy qz tx ty tz``; rigs.txt holds each sensor's pose in its rig,
``sensor_from_rig``, so that sensor_from_world = sensor_from_rig @ rig_from_world.
"""

import csv
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

from ..scene import CameraRecord, ImageRecord, SceneError, qvec_to_rotmat


def _rows(path: Path) -> List[List[str]]:
    if not path.is_file():
        return []
    with open(path) as f:
        return [[c.strip() for c in row] for row in csv.reader(f)
                if row and not row[0].lstrip().startswith("#")]


def _pose(values) -> np.ndarray:
    qw, qx, qy, qz, tx, ty, tz = (float(v) for v in values)
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
    for row in _rows(sensors_dir / "sensors.txt"):
        sensor_id, _, kind, *params = row
        if kind == "camera":
            model, w, h, *p = params
            cameras[sensor_id] = CameraRecord(model, int(w), int(h), tuple(float(v) for v in p))
    rigs: Dict[str, Dict[str, np.ndarray]] = {}
    for rig_id, sensor_id, *pose in _rows(sensors_dir / "rigs.txt"):
        rigs.setdefault(rig_id, {})[sensor_id] = _pose(pose)
    trajectories: Dict[Tuple[str, str], np.ndarray] = {
        (ts, dev): _pose(pose) for ts, dev, *pose in _rows(sensors_dir / "trajectories.txt")}
    images = []
    for ts, sensor_id, rel_path in _rows(sensors_dir / "records_camera.txt"):
        if sensor_id not in cameras:
            raise SceneError(f"Record {rel_path} uses unknown camera {sensor_id!r}.")
        pose = trajectories.get((ts, sensor_id))
        rig_id = None
        if pose is None:
            for rig_id, members in rigs.items():
                if sensor_id in members and (ts, rig_id) in trajectories:
                    pose = _compose(members[sensor_id], trajectories[(ts, rig_id)])
                    break
        if pose is None:
            raise SceneError(f"Image {rel_path} (timestamp {ts}, camera {sensor_id}) has no pose.")
        image_tags = {"camera": sensor_id, "timestamp": ts, **({"rig": rig_id} if rig_id else {}),
                      **dict(tags or {})}
        images.append(ImageRecord(rel_path, sensors_dir / "records_data" / rel_path, cameras[sensor_id],
                                  pose, image_tags))
    if not images:
        raise SceneError(f"No camera records in {sensors_dir / 'records_camera.txt'}.")
    return images
