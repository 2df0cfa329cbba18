"""instant-ngp / nerfstudio ``transforms.json``: per frame a ``file_path`` (relative to the file;
instant-ngp's may lack the extension) and a 4 x 4 camera-to-world ``transform_matrix`` in OpenGL
axes (x right, y up, z back); the intrinsics at the top level or per frame: ``fl_x``, ``fl_y``,
``cx``, ``cy``, ``w``, ``h`` (or instant-ngp's ``camera_angle_x``), and OpenCV distortion ``k1``,
``k2``, ``p1``, ``p2``. In COLMAP's terms: the camera's y and z axes negated, then inverted; an
OPENCV camera where there is distortion, else PINHOLE."""

import json
from pathlib import Path
from typing import List

import numpy as np

from pipeline.images import PHOTO_SUFFIXES, image_size
from pipeline.scene import CameraRecord, ImageRecord, SceneError

FLIP = np.diag([1.0, -1.0, -1.0])  # OpenGL camera axes to COLMAP's


def _camera(values: dict, path: Path, where: str) -> CameraRecord:
    width, height = (int(values["w"]), int(values["h"])) if "w" in values and "h" in values else image_size(path)
    if "fl_x" in values:
        fx = float(values["fl_x"])
    elif "camera_angle_x" in values:
        fx = 0.5 * width / np.tan(0.5 * float(values["camera_angle_x"]))
    else:
        raise SceneError(f"{where}: no focal length (fl_x or camera_angle_x).")
    fy = float(values.get("fl_y", fx))
    cx, cy = float(values.get("cx", width / 2)), float(values.get("cy", height / 2))
    distortion = [float(values.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2")]
    if any(distortion):
        return CameraRecord("OPENCV", width, height, (fx, fy, cx, cy, *distortion))
    return CameraRecord("PINHOLE", width, height, (fx, fy, cx, cy))


def read_transforms(path, tags=None) -> List[ImageRecord]:
    """The posed frames of a ``transforms.json``; image names relative to its folder."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise SceneError(f"{path}: not a transforms.json ({e}).") from None
    frames = data.get("frames") if isinstance(data, dict) else None
    if not frames:
        raise SceneError(f"{path}: no frames.")
    root = path.parent
    images = []
    for k, frame in enumerate(frames):
        where = f"{path}: frame {k}"
        name = str(frame.get("file_path", "")).removeprefix("./")
        file = root / name
        if not file.is_file():
            found = [root / (name + x) for s in PHOTO_SUFFIXES for x in (s, s.upper()) if (root / (name + x)).is_file()]
            if not found:
                raise SceneError(f"{where}: image {file} does not exist.")
            file = found[0]
            name = file.relative_to(root).as_posix()
        c2w = np.asarray(frame.get("transform_matrix"), np.float64)
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise SceneError(f"{where}: transform_matrix is not a finite 4x4 matrix.")
        R_c2w = c2w[:3, :3] @ FLIP  # the camera's axes in COLMAP's convention
        R = R_c2w.T
        camera = _camera({**data, **frame}, file, where)
        images.append(ImageRecord(name, file, camera, np.concatenate([R, (-R @ c2w[:3, 3])[:, None]], 1),
                                  dict(tags or {})))
    return images
