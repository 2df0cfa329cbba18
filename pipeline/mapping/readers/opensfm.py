"""OpenSfM ``reconstruction.json``: a list of reconstructions, each with ``cameras`` (a
``perspective`` camera has ``width``, ``height``, ``focal`` as a fraction of the larger side, and
``k1``, ``k2`` on the normalised point) and ``shots`` (per image, ``camera``, ``rotation`` as an
axis-angle vector and ``translation``: world to camera, OpenCV axes). In COLMAP's terms a RADIAL
camera (f = focal x the larger side, the image centre, k1, k2)."""

import json
from pathlib import Path
from typing import List

import numpy as np

from pipeline.scene import CameraRecord, ImageRecord, SceneError


def axis_angle(v) -> np.ndarray:
    """The rotation matrix of an axis-angle vector (Rodrigues)."""
    v = np.asarray(v, np.float64)
    angle = np.linalg.norm(v)
    if angle < 1e-12:
        return np.eye(3)
    k = v / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def read_opensfm(reconstruction, image_root, tags=None) -> List[ImageRecord]:
    """The shots of the largest reconstruction in ``reconstruction`` with their images in
    ``image_root`` (shots whose image is absent are left out)."""
    reconstruction, image_root = Path(reconstruction), Path(image_root)
    try:
        models = json.loads(reconstruction.read_text())
    except (OSError, ValueError) as e:
        raise SceneError(f"{reconstruction}: not an OpenSfM reconstruction ({e}).") from None
    if not isinstance(models, list) or not models:
        raise SceneError(f"{reconstruction}: expected a list of reconstructions.")
    model = max(models, key=lambda m: len(m.get("shots", {})))
    images = []
    for name, shot in sorted(model["shots"].items()):
        cam = model["cameras"].get(shot.get("camera"))
        if cam is None:
            raise SceneError(f"{reconstruction}: shot {name} names camera {shot.get('camera')!r}, which is not listed.")
        if cam.get("projection_type", "perspective") not in ("perspective", "brown"):
            raise SceneError(f"{reconstruction}: camera {shot['camera']!r} is a {cam['projection_type']!r} camera; "
                             "only perspective cameras are read.")
        path = image_root / name
        if not path.is_file():
            continue
        w, h = int(cam["width"]), int(cam["height"])
        f = float(cam["focal"]) * max(w, h)
        camera = CameraRecord("RADIAL", w, h, (f, w / 2, h / 2, float(cam.get("k1", 0)), float(cam.get("k2", 0))))
        R, t = axis_angle(shot["rotation"]), np.asarray(shot["translation"], np.float64)
        images.append(ImageRecord(name, path, camera, np.concatenate([R, t[:, None]], 1), dict(tags or {})))
    if not images:
        raise SceneError(f"{reconstruction}: none of its shots has its image in {image_root}.")
    return images
