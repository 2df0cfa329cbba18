"""Middlebury multi-view stereo (Seitz et al. 2006): ``NAME_par.txt`` lists, after the number of
views, one line per view ``image k11..k33 r11..r33 t1 t2 t3`` with P = K [R | t] (world to
camera, OpenCV axes). A file lists every view of the dataset; the images present are used."""

from pathlib import Path
from typing import List, Optional

import numpy as np

from pipeline.images import image_size
from pipeline.scene import CameraRecord, ImageRecord, SceneError
from pipeline.textfiles import read_text


def par_file(root: Path) -> Path:
    """The one ``*_par.txt`` of a Middlebury folder."""
    found = sorted(Path(root).glob("*_par.txt"))
    if len(found) != 1:
        raise SceneError(f"{root}: expected one Middlebury '*_par.txt' file, found {len(found)}.")
    return found[0]


def read_middlebury(root, par: Optional[Path] = None, tags=None) -> List[ImageRecord]:
    """Posed images of a Middlebury folder (images beside their ``*_par.txt``); views whose image
    is absent are left out. Errors name the file and line."""
    root = Path(root)
    par = Path(par) if par is not None else par_file(root)
    lines = read_text(par, "Middlebury camera file").splitlines()
    views = [(n, line.split()) for n, line in enumerate(lines[1:], 2) if line.split()]
    try:
        declared = int(lines[0]) if lines else -1
    except ValueError:
        declared = -1
    if declared < 0:
        raise SceneError(f"{par}:1: expected the number of views, got {(lines or [''])[0].strip()[:40]!r}.")
    if declared != len(views):
        raise SceneError(f"{par}: its header says {declared} views but it lists {len(views)}: the file is cut "
                         "short or has extra lines.")
    images = []
    for n, fields in views:
        if len(fields) != 22:
            raise SceneError(f"{par}:{n}: expected an image name and 21 numbers (K, R, t), got {len(fields)} fields.")
        try:
            values = np.array(fields[1:], dtype=np.float64)
        except ValueError:
            raise SceneError(f"{par}:{n}: a value is not a number.") from None
        path = root / fields[0]
        if not path.is_file():
            continue
        K, R, t = values[:9].reshape(3, 3), values[9:18].reshape(3, 3), values[18:]
        if abs(K[0, 1]) > 1e-9 or K[2, 2] != 1:
            raise SceneError(f"{par}:{n}: K has a skew or is not normalised, which no COLMAP camera model holds.")
        width, height = image_size(path)
        camera = CameraRecord("PINHOLE", width, height, tuple(float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])))
        images.append(ImageRecord(fields[0], path, camera, np.concatenate([R, t[:, None]], 1), dict(tags or {}),
                                  origin=f"{par}:{n}"))
    if not images:
        raise SceneError(f"{par}: none of its {len(lines) - 1} views has its image in {root}.")
    return images
