"""Rigs in the generated courtyard (``pipeline.data.synthetic``): a multi-camera rig rendered at the
query poses of each condition, for evaluating localization of a rig as one body.

The rig's frame is its middle camera's (x right, y down, z forward); camera i is turned ``yaw[i]``
degrees about the rig's vertical and stands ``baseline[i]`` metres along the rig's x axis. The default,
three cameras 55 degrees apart 15 cm apart, covers about 175 degrees with the demo's 65 degree lenses
(the views overlap by about 10 degrees). Every camera of a frame is rendered in the frame's condition
(occluders in front of each camera for ``occluded``).

Written: ``rigs/<condition>/<frame>/cam<i>.png`` and ``rigs.json`` (the generation settings, the rig's
cam_from_rig, and per frame its condition, rig_from_world and image names), reused when the settings
match.
"""

import json
import math
from pathlib import Path
from typing import List, Sequence, Tuple

import numpy as np

from pipeline.data.synthetic import CONDITIONS, SyntheticConfig, SyntheticScene, area
from pipeline.localization.bodies import compose
from pipeline.queries import QueryRecord
from pipeline.scene import CameraRecord

RIG_YAWS = (-55.0, 0.0, 55.0)
RIG_BASELINE = (-0.15, 0.0, 0.15)


def rig_cameras(yaws: Sequence[float] = RIG_YAWS, offsets: Sequence[float] = RIG_BASELINE) -> List[np.ndarray]:
    """cam_from_rig (3 x 4) of each camera."""
    out = []
    for yaw, x in zip(yaws, offsets):
        a = math.radians(yaw)
        R = np.array([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]])
        out.append(np.concatenate([R, (-R @ np.array([x, 0.0, 0.0]))[:, None]], 1))
    return out


def generate_rig_frames(root, conf: SyntheticConfig, camera: CameraRecord, frames_per_condition: int,
                        spread: float = 0.5, yaws: Sequence[float] = RIG_YAWS,
                        offsets: Sequence[float] = RIG_BASELINE, conditions: Sequence[str] = CONDITIONS) -> Path:
    """Render the rig at ``frames_per_condition`` query poses of each condition into ``root`` (see the
    module docstring); the frames of a condition (of ``conditions``) are the demo's query poses of that
    condition (the same seeds), as the rig's pose."""
    import cv2
    root = Path(root)
    generation = json.loads(json.dumps({"config": dict(conf.__dict__), "camera": camera.to_json(),
                                        "frames_per_condition": frames_per_condition, "spread": spread,
                                        "yaws": list(yaws), "offsets": list(offsets),
                                        "conditions": list(conditions)}))
    meta = root / "rigs.json"
    if meta.is_file():
        try:
            if json.loads(meta.read_text()).get("generation") == generation:
                return root
        except ValueError:
            pass
    scene = SyntheticScene(conf)
    cams = rig_cameras(yaws, offsets)
    frames = []
    for c, condition in enumerate(CONDITIONS):
        if condition not in conditions:
            continue
        for j, body in enumerate(scene.query_poses(frames_per_condition, seed=conf.seed * 100 + c, spread=spread)):
            names = []
            for i, C in enumerate(cams):
                rgb, _ = scene.render(camera, compose(C, body), condition,
                                      seed=conf.seed * 1000 + 700 + 40 * c + 4 * j + i)
                name = f"rigs/{condition}/{j:04d}/cam{i}.png"
                (root / name).parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(root / name), rgb[..., ::-1])
                names.append(name)
            frames.append({"key": f"{condition}/{j:04d}", "condition": condition, "rig_from_world": body.tolist(),
                           "images": names})
    meta.write_text(json.dumps({"generation": generation, "cam_from_rig": [C.tolist() for C in cams],
                                "frames": frames}, indent=1))
    return root


def read_rig_frames(root, camera: CameraRecord) -> List[Tuple[str, str, List[QueryRecord], List[np.ndarray]]]:
    """(key, condition, the images as QueryRecords with ground truth, cam_from_rig) of each frame."""
    root = Path(root)
    doc = json.loads((root / "rigs.json").read_text())
    cams = [np.asarray(C, np.float64) for C in doc["cam_from_rig"]]
    out = []
    for f in doc["frames"]:
        body = np.asarray(f["rig_from_world"], np.float64)
        queries = []
        for name, C in zip(f["images"], cams):
            T = compose(C, body)
            queries.append(QueryRecord(name, root / name, camera, {"condition": f["condition"], "area": area(T)}, T))
        out.append((f["key"], f["condition"], queries, cams))
    return out
