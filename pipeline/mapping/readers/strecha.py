"""Strecha et al. 2008 multi-view benchmark: images with ground-truth cameras, no points."""

from pathlib import Path
from typing import List

import numpy as np

from pipeline.scene import CameraRecord, ImageRecord, SceneError
from pipeline.textfiles import read_text


def read_strecha_camera(path) -> tuple:
    """A ``*.camera`` file: K (3 rows), distortion, R camera-to-world (3 rows), centre, size.

    Returns (CameraRecord PINHOLE, cam_from_world (3, 4)).
    """
    text = read_text(path, "Strecha camera file")
    try:
        values = np.array(text.split(), dtype=np.float64)
    except ValueError as e:
        raise SceneError(f"{path}: not a Strecha camera file ({e})") from None
    if values.size != 9 + 3 + 9 + 3 + 2:
        raise SceneError(f"{path}: expected 26 numbers in a Strecha camera file, got {values.size}.")
    K, R_c2w, centre, (w, h) = values[:9].reshape(3, 3), values[12:21].reshape(3, 3), values[21:24], values[24:]
    R = R_c2w.T
    # K is in pixel-corner coordinates like COLMAP's (an assumption we test via reprojection).
    if not np.isfinite(values).all() or w != int(w) or h != int(h):
        raise SceneError(f"{path}: a Strecha camera file needs finite numbers and a whole image size")
    camera = CameraRecord("PINHOLE", int(w), int(h), (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    return camera, np.concatenate([R, (-R @ centre)[:, None]], 1)


def read_strecha(root, tags=None) -> List[ImageRecord]:
    """Posed images of one Strecha scene (``images/*.jpg`` + ``gt_dense_cameras/*.camera``)."""
    root = Path(root)
    images = []
    for path in sorted((root / "images").glob("*.jpg")):
        cam_file = root / "gt_dense_cameras" / f"{path.name}.camera"
        if not cam_file.is_file():
            raise SceneError(f"No ground-truth camera {cam_file} for image {path}.")
        camera, pose = read_strecha_camera(cam_file)
        images.append(ImageRecord(path.name, path, camera, pose, dict(tags or {})))
    if not images:
        raise SceneError(f"No images found in {root / 'images'}.")
    return images
