"""OpenSfM ``reconstruction.json``: a list of reconstructions, each with ``cameras`` (a
``perspective`` camera has ``width``, ``height``, ``focal`` as a fraction of the larger side, and
``k1``, ``k2`` on the normalised point; ``brown`` and ``fisheye`` cameras too: ``opensfm_camera``)
and ``shots`` (per image, ``camera``, ``rotation`` as an axis-angle vector and ``translation``:
world to camera, OpenCV axes). In COLMAP's terms a perspective camera is RADIAL (f = focal x the
larger side, the image centre, k1, k2)."""

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


PROJECTIONS = ("perspective", "brown", "fisheye")


def opensfm_camera(cam: dict) -> CameraRecord:
    """An OpenSfM camera in COLMAP's terms. Its values are normalised by the larger image side
    ``s``, from the image centre: a pixel coordinate is ``u = x s + w / 2``. ``perspective``
    (focal, k1, k2): RADIAL; ``brown`` (focal_x, focal_y, c_x, c_y, k1, k2, p1, p2, k3: OpenCV's
    distortion): OPENCV, or FULL_OPENCV with k3; ``fisheye`` (focal, k1, k2 on the angle):
    OPENCV_FISHEYE. KeyError or ValueError for a missing or bad value; ValueError for another
    projection (spherical ...)."""
    kind = cam.get("projection_type", "perspective")
    if kind not in PROJECTIONS:
        raise ValueError(f"a {kind!r} camera is not read (known: {', '.join(PROJECTIONS)})")
    w, h = int(cam["width"]), int(cam["height"])
    s = max(w, h)

    def value(key, default=None):
        v = float(cam[key] if default is None else cam.get(key, default))
        if not np.isfinite(v):
            raise ValueError(f"{key} is {v}")
        return v
    if kind == "perspective":
        return CameraRecord("RADIAL", w, h, (value("focal") * s, w / 2, h / 2, value("k1", 0), value("k2", 0)))
    if kind == "fisheye":
        f = value("focal") * s
        return CameraRecord("OPENCV_FISHEYE", w, h, (f, f, w / 2, h / 2, value("k1", 0), value("k2", 0), 0.0, 0.0))
    fx, fy = value("focal_x") * s, value("focal_y") * s
    cx, cy = w / 2 + value("c_x", 0) * s, h / 2 + value("c_y", 0) * s
    k1, k2, p1, p2, k3 = (value(k, 0) for k in ("k1", "k2", "p1", "p2", "k3"))
    if k3:
        return CameraRecord("FULL_OPENCV", w, h, (fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0))
    return CameraRecord("OPENCV", w, h, (fx, fy, cx, cy, k1, k2, p1, p2))


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
        path = image_root / name
        if not path.is_file():
            continue
        try:
            camera = opensfm_camera(cam)
            rotation = np.asarray(shot["rotation"], np.float64).reshape(3)
            t = np.asarray(shot["translation"], np.float64).reshape(3)
        except (KeyError, TypeError, ValueError, OverflowError) as e:
            raise SceneError(f"{where}: its camera {camera_id!r} or pose is not numbers of the right size "
                             f"({type(e).__name__}: {e}).") from None
        if not (np.isfinite(rotation).all() and np.isfinite(t).all()):
            raise SceneError(f"{where}: its rotation or translation is not finite.")
        with np.errstate(over="ignore", invalid="ignore"):  # a huge rotation: refused by posed_images' check
            R = axis_angle(rotation)
        images.append(ImageRecord(name, path, camera, np.concatenate([R, t[:, None]], 1),
                                  dict(tags or {}), origin=where))
    if not images:
        raise SceneError(f"{reconstruction}: none of its shots has its image in {image_root}.")
    return images
