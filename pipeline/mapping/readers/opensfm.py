"""OpenSfM ``reconstruction.json``: a list of reconstructions, each with ``cameras`` (a
``perspective`` camera has ``width``, ``height``, ``focal`` as a fraction of the larger side, and
``k1``, ``k2`` on the normalised point) and ``shots`` (per image, ``camera``, ``rotation`` as an
axis-angle vector and ``translation``: world to camera, OpenCV axes). In COLMAP's terms a RADIAL
camera (f = focal x the larger side, the image centre, k1, k2)."""

from pathlib import Path
from typing import List

import numpy as np

from pipeline.scene import CameraRecord, ImageRecord, SceneError
from pipeline.textfiles import read_json


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
    models = read_json(reconstruction, "OpenSfM reconstruction", list)
    models = [m for m in models if isinstance(m, dict) and isinstance(m.get("shots"), dict)
              and isinstance(m.get("cameras"), dict)]
    if not models:
        raise SceneError(f"{reconstruction}: expected a list of reconstructions (objects with shots and cameras).")
    model = max(models, key=lambda m: len(m["shots"]))
    images = []
    for name, shot in sorted(model["shots"].items()):
        where = f"{reconstruction}: shot {name}"
        camera_id = shot.get("camera") if isinstance(shot, dict) else None
        cam = model["cameras"].get(camera_id) if isinstance(camera_id, str) else None
        if not isinstance(cam, dict):
            raise SceneError(f"{where} names camera {camera_id!r}, which is not listed.")
        if cam.get("projection_type", "perspective") not in ("perspective", "brown"):
            raise SceneError(f"{reconstruction}: camera {shot['camera']!r} is a {cam['projection_type']!r} camera; "
                             "only perspective cameras are read.")
        path = image_root / name
        if not path.is_file():
            continue
        try:
            w, h = int(cam["width"]), int(cam["height"])
            f = float(cam["focal"]) * max(w, h)
            params = (f, w / 2, h / 2, float(cam.get("k1", 0)), float(cam.get("k2", 0)))
            rotation = np.asarray(shot["rotation"], np.float64).reshape(3)
            t = np.asarray(shot["translation"], np.float64).reshape(3)
        except (KeyError, TypeError, ValueError, OverflowError) as e:
            raise SceneError(f"{where}: its camera or pose is not numbers of the right size "
                             f"({type(e).__name__}: {e}).") from None
        if not (np.isfinite(rotation).all() and np.isfinite(t).all()):
            raise SceneError(f"{where}: its rotation or translation is not finite.")
        camera = CameraRecord("RADIAL", w, h, params)
        with np.errstate(over="ignore", invalid="ignore"):  # a huge rotation: refused by posed_images' check
            R = axis_angle(rotation)
        images.append(ImageRecord(name, path, camera, np.concatenate([R, t[:, None]], 1),
                                  dict(tags or {})))
    if not images:
        raise SceneError(f"{reconstruction}: none of its shots has its image in {image_root}.")
    return images
