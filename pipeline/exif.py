"""Intrinsics of uncalibrated photos from their EXIF, as COLMAP's image reader derives them.

In order: the 35 mm equivalent focal length (``FocalLengthIn35mmFilm``: f_px = f35 / 35 x the
larger image side), else the focal length in mm with the focal plane resolution (pixels per
unit of the sensor), else a default of ``DEFAULT_FOCAL_FACTOR`` x the larger side (COLMAP's
prior, about 45 degrees across the larger side). The principal point is the image centre. The
size is that of the image as decoded (EXIF orientation applied, as ``read_image`` does).
"""

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence

from pipeline.scene import CameraRecord

DEFAULT_FOCAL_FACTOR = 1.2
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
_EXIF_IFD = 0x8769
_FOCAL_LENGTH, _FOCAL_35MM = 37386, 41989
_PLANE_X_RES, _PLANE_UNIT = 41486, 41488
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # EXIF FocalPlaneResolutionUnit: inch, cm, mm, um


@dataclass(frozen=True)
class ExifCamera:
    name: str
    camera: CameraRecord
    source: str  # "35mm-equivalent", "focal-plane", "default"


def _positive(value) -> Optional[float]:
    try:
        v = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return v if v > 0 else None


def exif_camera(path, name: Optional[str] = None, default_factor: float = DEFAULT_FOCAL_FACTOR) -> ExifCamera:
    """The SIMPLE_PINHOLE camera of one image file. The file is read as localize reads it
    (``pipeline.images.read_image``: header, pixel limit, full decode), so that a list never holds
    an image that localize would refuse; OSError/ValueError naming the file otherwise."""
    import warnings

    from PIL import Image

    from pipeline.images import read_image

    height, width = read_image(path).shape[:2]  # EXIF orientation applied, as localize decodes
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                exif = im.getexif()
                sub = exif.get_ifd(_EXIF_IFD)
    except Exception:  # noqa: BLE001 - decoded by OpenCV but no EXIF PIL can read: the default focal
        sub = {}
    size = max(width, height)
    focal, source = None, "default"
    f35 = _positive(sub.get(_FOCAL_35MM))
    if f35:
        focal, source = f35 / 35.0 * size, "35mm-equivalent"
    else:
        f_mm, res = _positive(sub.get(_FOCAL_LENGTH)), _positive(sub.get(_PLANE_X_RES))
        unit = _UNIT_MM.get(int(sub.get(_PLANE_UNIT, 2)))
        if f_mm and res and unit:
            focal, source = f_mm * res / unit, "focal-plane"
    if focal is None:
        focal = default_factor * size
    camera = CameraRecord("SIMPLE_PINHOLE", width, height, (focal, width / 2, height / 2))
    return ExifCamera(name or Path(path).name, camera, source)


def find_images(paths: Sequence[Path]) -> List[tuple]:
    """(name, path) of the images under folders (name relative to the folder, recursively) and
    of single files (name: the file name), sorted by name; repeated names are refused."""
    found = []
    for p in map(Path, paths):
        if p.is_dir():
            found += [(f.relative_to(p).as_posix(), f) for f in sorted(p.rglob("*"))
                      if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES]
        elif p.is_file():
            found.append((p.name, p))
        else:
            raise ValueError(f"{p} does not exist.")
    names = [n for n, _ in found]
    if len(set(names)) != len(names):
        raise ValueError(f"Images with the same name: {sorted({n for n in names if names.count(n) > 1})[:5]}; "
                         "pass their common folder instead.")
    return sorted(found)


def format_line(cam: ExifCamera) -> str:
    """A line of a query list with intrinsics: ``name MODEL width height params...``."""
    c = cam.camera
    return " ".join([cam.name, c.model, str(c.width), str(c.height), *(f"{p:.6g}" for p in c.params)])
