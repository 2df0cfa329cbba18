"""instant-ngp / nerfstudio ``transforms.json``: per frame a ``file_path`` (relative to the file;
instant-ngp's may lack the extension) and a 4 x 4 camera-to-world ``transform_matrix`` in OpenGL
axes (x right, y up, z back); the intrinsics at the top level or per frame: ``fl_x``, ``fl_y``,
``cx``, ``cy``, ``w``, ``h`` (or instant-ngp's ``camera_angle_x``), ``camera_model`` (nerfstudio's:
OPENCV by default, or OPENCV_FISHEYE) and distortion ``k1`` .. ``k4``, ``p1``, ``p2``. In COLMAP's
terms: the camera's y and z axes negated, then inverted; an OPENCV_FISHEYE camera for a fisheye, else
OPENCV where there is distortion (FULL_OPENCV with k3), else PINHOLE; a model or distortion term that
COLMAP's models cannot hold is refused, never dropped."""

import json
from pathlib import Path
from typing import List

import numpy as np

from pipeline.images import PHOTO_SUFFIXES, image_size
from pipeline.scene import CameraRecord, ImageRecord, SceneError
from pipeline.textfiles import read_json

FLIP = np.diag([1.0, -1.0, -1.0])  # OpenGL camera axes to COLMAP's
# nerfstudio's camera_model values of a perspective camera (its default: OPENCV); OPENCV_FISHEYE is the
# other one read, every other (EQUIRECTANGULAR, ...) is refused
PERSPECTIVE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")


def _number(values: dict, key: str, where: str, default=None) -> float:
    """``values[key]`` as a finite number (``default`` where it is absent), or SceneError naming it."""
    value = values.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise SceneError(f"{where}: {key} is {json.dumps(value)}, not a finite number.")
    return float(value)


def _camera(values: dict, path: Path, where: str) -> CameraRecord:
    if "w" in values and "h" in values:
        width, height = (_number(values, k, where) for k in ("w", "h"))
        if width != int(width) or height != int(height):
            raise SceneError(f"{where}: the image size {width:g} x {height:g} is not in whole pixels.")
        width, height = int(width), int(height)
    else:
        width, height = image_size(path)
    if "fl_x" in values:
        fx = _number(values, "fl_x", where)
    elif "camera_angle_x" in values:
        angle = _number(values, "camera_angle_x", where)
        if not 0 < angle < np.pi:
            raise SceneError(f"{where}: camera_angle_x is {angle:g}, not a field of view in radians (0 to pi).")
        fx = 0.5 * width / np.tan(0.5 * angle)
    else:
        raise SceneError(f"{where}: no focal length (fl_x or camera_angle_x).")
    fy = _number(values, "fl_y", where, fx)
    cx, cy = _number(values, "cx", where, width / 2), _number(values, "cy", where, height / 2)
    k = {key: _number(values, key, where, 0.0) for key in ("k1", "k2", "k3", "k4", "p1", "p2")}
    model = values.get("camera_model", "OPENCV")
    if model == "OPENCV_FISHEYE":
        if k["p1"] or k["p2"]:
            raise SceneError(f"{where}: an OPENCV_FISHEYE camera has no tangential distortion (p1, p2).")
        return CameraRecord("OPENCV_FISHEYE", width, height, (fx, fy, cx, cy, k["k1"], k["k2"], k["k3"], k["k4"]))
    if model not in PERSPECTIVE_MODELS:
        raise SceneError(f"{where}: camera_model {json.dumps(model)} is not read (known: OPENCV_FISHEYE, "
                         f"{', '.join(PERSPECTIVE_MODELS)}).")
    if k["k4"]:  # nerfstudio's k4 is a radial term in r^8, which no COLMAP camera model holds
        raise SceneError(f"{where}: k4 = {k['k4']:g} on a {model} camera (a radial term in r^8) has no COLMAP "
                         "camera model.")
    if k["k3"]:
        return CameraRecord("FULL_OPENCV", width, height,
                            (fx, fy, cx, cy, k["k1"], k["k2"], k["p1"], k["p2"], k["k3"], 0.0, 0.0, 0.0))
    if any(k[key] for key in ("k1", "k2", "p1", "p2")):
        return CameraRecord("OPENCV", width, height, (fx, fy, cx, cy, k["k1"], k["k2"], k["p1"], k["p2"]))
    return CameraRecord("PINHOLE", width, height, (fx, fy, cx, cy))


def read_transforms(path, tags=None) -> List[ImageRecord]:
    """The posed frames of a ``transforms.json``; image names relative to its folder."""
    path = Path(path)
    data = read_json(path, "transforms.json")
    frames = data.get("frames")
    if not frames or not isinstance(frames, list):
        raise SceneError(f"{path}: no frames (a list of them).")
    root = path.parent
    images = []
    for k, frame in enumerate(frames):
        where = f"{path}: frame {k}"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise SceneError(f"{where}: expected an object with a file_path, got {json.dumps(frame)[:80]}.")
        name = frame["file_path"].removeprefix("./")
        file = root / name
        if not file.is_file():
            found = [root / (name + x) for s in PHOTO_SUFFIXES for x in (s, s.upper()) if (root / (name + x)).is_file()]
            if not found:
                raise SceneError(f"{where}: image {file} does not exist.")
            file = found[0]
            name = file.relative_to(root).as_posix()
        try:
            c2w = np.asarray(frame.get("transform_matrix"), np.float64)
        except (TypeError, ValueError):
            c2w = np.zeros(0)
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise SceneError(f"{where}: transform_matrix is not a finite 4x4 matrix.")
        R_c2w = c2w[:3, :3] @ FLIP  # the camera's axes in COLMAP's convention
        R = R_c2w.T
        camera = _camera({**data, **frame}, file, where)
        images.append(ImageRecord(name, file, camera, np.concatenate([R, (-R @ c2w[:3, 3])[:, None]], 1),
                                  dict(tags or {}), origin=where))
    return images
