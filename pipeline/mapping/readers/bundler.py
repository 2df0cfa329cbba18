"""Bundler (Snavely et al. 2006) ``bundle.out`` v0.3: per camera ``f k1 k2``, R (3 rows) and t;
a camera with f = 0 was not reconstructed. Bundler's camera looks down -z with y up and measures
image points from the image centre, y up; its distortion 1 + k1 r^2 + k2 r^4 acts on the
normalised point. In COLMAP's terms: R and t with their y and z rows negated, and a RADIAL camera
(f, the image centre, k1, k2). Images are named by an image list (``list.txt``, one name per
line, optionally followed by a focal length), else taken in name order from the folder."""

from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np

from pipeline.images import image_files, image_size
from pipeline.scene import CameraRecord, ImageRecord, SceneError
from pipeline.textfiles import read_text

FLIP = np.diag([1.0, -1.0, -1.0])  # Bundler's camera axes (x right, y up, z back) to COLMAP's


def image_list(root: Path, list_file: Optional[Path] = None) -> List[str]:
    """The names of the bundle's cameras, in order."""
    if list_file is not None and Path(list_file).is_file():
        return [line.split()[0] for line in read_text(list_file, "Bundler image list").splitlines() if line.strip()]
    return image_files(root)


def read_bundler(bundle, image_root, names: Optional[Sequence[str]] = None, tags=None) -> List[ImageRecord]:
    """The reconstructed cameras of ``bundle`` (a ``bundle.out``) with their images in
    ``image_root``; ``names``: the images of the cameras, in order (default: ``image_list``).
    Errors name the file and line."""
    bundle, image_root = Path(bundle), Path(image_root)
    lines = read_text(bundle, "Bundler bundle file").splitlines()
    body = [(n, line) for n, line in enumerate(lines, 1) if line.strip() and not line.startswith("#")]
    if not body:
        raise SceneError(f"{bundle}: empty bundle file.")
    try:
        num_cameras, _ = (int(v) for v in body[0][1].split())
    except ValueError:
        raise SceneError(f"{bundle}:{body[0][0]}: expected 'num_cameras num_points'.") from None
    names = list(names) if names is not None else image_list(image_root, bundle.parent / "list.txt")
    if len(names) < num_cameras:
        raise SceneError(f"{bundle}: {num_cameras} cameras but {len(names)} images in {image_root}: give the "
                         "image list (list.txt) the bundle was made from.")
    images = []
    for c in range(num_cameras):
        rows = body[1 + 5 * c: 6 + 5 * c]
        if len(rows) < 5:
            raise SceneError(f"{bundle}: camera {c} is cut short (5 lines each: f k1 k2, R, t).")
        try:
            values = np.array([[float(v) for v in line.split()] for _, line in rows])
        except ValueError:
            raise SceneError(f"{bundle}:{rows[0][0]}: camera {c} holds a value that is not a number.") from None
        if values.shape != (5, 3):
            raise SceneError(f"{bundle}:{rows[0][0]}: camera {c}: expected 5 lines of 3 numbers.")
        (f, k1, k2), R, t = values[0], values[1:4], values[4]
        if f == 0:  # not reconstructed
            continue
        path = image_root / names[c]
        width, height = image_size(path)
        camera = CameraRecord("RADIAL", width, height, tuple(float(v) for v in (f, width / 2, height / 2, k1, k2)))
        images.append(ImageRecord(names[c], path, camera, np.concatenate([FLIP @ R, (FLIP @ t)[:, None]], 1),
                                  dict(tags or {}), origin=f"{bundle}:{rows[0][0]} (camera {c})"))
    if not images:
        raise SceneError(f"{bundle}: no camera was reconstructed (every focal length is 0).")
    return images
