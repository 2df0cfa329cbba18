"""LLFF ``poses_bounds.npy`` (Mildenhall et al. 2019, the NeRF datasets): per image 17 numbers,
a 3 x 5 matrix [R | t | (h, w, f)] camera-to-world, row by row, then the near and far depths. R's
columns are the camera's down, right and backward axes; in COLMAP's terms (right, down, forward):
columns 1, 0 and minus 2. The images are those of ``images/`` in name order, one per row; h, w and
f are in pixels of the images the poses were made for (rescaled to the files' size)."""

import dataclasses
from pathlib import Path
from tokenize import TokenError
from typing import List

import numpy as np

from pipeline.images import image_files, image_size
from pipeline.scene import CameraRecord, ImageRecord, SceneError


def read_llff(root, tags=None) -> List[ImageRecord]:
    """Posed images of an LLFF scene folder (``poses_bounds.npy`` and ``images/``)."""
    root = Path(root)
    path = root / "poses_bounds.npy"
    if not path.is_file():
        raise SceneError(f"{path}: no LLFF poses_bounds.npy there.")
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, SyntaxError, TokenError) as e:  # a damaged header or body
        raise SceneError(f"{path}: not an LLFF poses_bounds.npy ({type(e).__name__}: {e}).") from None
    if data.ndim != 2 or data.shape[1] != 17:
        raise SceneError(f"{path}: expected N x 17 finite numbers (3 x 5 pose, near, far), got {data.shape}.")
    bad = np.flatnonzero(~np.isfinite(data).all(1)) if data.dtype.kind in "fc" else []
    if len(bad) or data.dtype.kind not in "fiuc":
        rows = f"row {bad[0]} (of rows 0-{len(data) - 1})" if len(bad) else f"values of type {data.dtype}"
        raise SceneError(f"{path}: expected N x 17 finite numbers (3 x 5 pose, near, far): {rows} is not"
                         f"{' finite' if len(bad) else ' numbers'}"
                         f"{f' ({len(bad)} rows in all)' if len(bad) > 1 else ''}.")
    names = image_files(root / "images")
    if len(names) != len(data):
        raise SceneError(f"{path}: {len(data)} poses for {len(names)} images in {root / 'images'}.")
    images = []
    for k, (name, row) in enumerate(zip(names, data)):
        with np.errstate(over="ignore", invalid="ignore"):  # huge values: a pose that is not finite,
            images.append(dataclasses.replace(_image(root, path, name, row, tags),  # refused by posed_images' check
                                              origin=f"{path}: row {k}"))
    return images


def _image(root: Path, path: Path, name: str, row: np.ndarray, tags) -> ImageRecord:
    """One row of ``poses_bounds.npy`` as the image ``name``'s record."""
    m = row[:15].reshape(3, 5)
    c2w = np.stack([m[:, 1], m[:, 0], -m[:, 2]], 1)  # (down, right, back) -> (right, down, forward)
    h, w, f = m[:, 4]
    if not min(h, w, f) > 0:
        raise SceneError(f"{path}: image {name}: its size {w:g} x {h:g} and focal length {f:g} must be positive.")
    file = root / "images" / name
    width, height = image_size(file)
    s = width / w
    if abs(height / h - s) > 1e-3 * s:
        raise SceneError(f"{path}: image {name} is {width}x{height}, not of the aspect of the poses' {w:g}x{h:g}.")
    R = c2w.T
    camera = CameraRecord("SIMPLE_PINHOLE", width, height, (float(f * s), width / 2, height / 2))
    return ImageRecord(name, file, camera, np.concatenate([R, (-R @ m[:, 3])[:, None]], 1), dict(tags or {}))
