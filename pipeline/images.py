"""Image reading and resizing, as official PixLoc does them (OpenCV), and file digests.

Every image the pipeline uses (queries, map images, training and report images) is read by
``read_image``: the header first (an empty file, a file that is no image, or one above
``max_image_pixels()`` is refused before anything is decoded: a 2 MB PNG can declare 30000 x
30000 pixels), then a full decode whose every error, of any decoder, is an ``ImageReadError``
naming the file. ``read_image_for`` also fits the file to the camera that describes it, the same
way for queries and map images (``fit_image``).
"""

import hashlib
import os
import re
import struct
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import cv2
import numpy as np
import torch

from pipeline.runtime import DEFAULT_MAX_IMAGE_PIXELS, MAX_PIXELS_ENV, current  # noqa: F401


class ImageReadError(IOError):
    """An image file that is missing, too large, or cannot be decoded."""


# A documented ceiling on the pixels of one image, checked from the header before decoding
# (150 MP: a 12,000 x 12,500 photo; decoding it takes 0.45 GB, resizing 1.8 GB). Raise it with
# the environment variable PIXLOC_MAX_IMAGE_PIXELS (inherited by local Dask workers) or the
# command line's --max-image-pixels, which sets that variable.

# What libjpeg and libpng print (they do not fail) when a file is truncated or corrupt: OpenCV
# then returns a partly grey image as if nothing happened.
_DECODER_ERRORS = ("Corrupt JPEG data", "Premature end of JPEG file", "JPEG datastream contains no image",
                   "libpng error", "Invalid SOS parameters", "Bogus marker length", "Huffman")
_STDERR_LOCK = threading.Lock()
_PIL_LOCK = threading.Lock()
_ROTATED = (5, 6, 7, 8)  # EXIF orientations that swap width and height


def max_image_pixels() -> int:
    """The pixel limit in force (``pipeline.runtime.RunSettings``: --max-image-pixels, else
    PIXLOC_MAX_IMAGE_PIXELS, else DEFAULT_MAX_IMAGE_PIXELS)."""
    return current().max_image_pixels


@dataclass(frozen=True)
class ImageHeader:
    """What a file's header says: its size as stored (pixels) and its EXIF orientation (1-8)."""

    width: int
    height: int
    orientation: int = 1

    @property
    def oriented_size(self) -> Tuple[int, int]:
        """(width, height) once the EXIF orientation is applied (as ``read_image`` decodes)."""
        return (self.height, self.width) if self.orientation in _ROTATED else (self.width, self.height)


def read_header(path) -> Optional[ImageHeader]:
    """The header of an image file, without decoding its pixels; None for a format that PIL
    cannot identify (OpenCV may still decode it). Refuses a missing or empty file, and one whose
    pixels exceed ``max_image_pixels()``, with an ImageReadError naming the file."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise ImageReadError(f"image file {path} is missing" + (" (it is a folder)" if path.is_dir() else ""))
    if path.stat().st_size == 0:
        raise ImageReadError(f"image file {path} is empty (0 bytes)")
    limit = max_image_pixels()
    try:
        with _PIL_LOCK:  # PIL's own ceiling is a global: ours, from the header, replaces it here
            saved, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
            try:
                with Image.open(path) as im:
                    width, height = im.size
                    try:
                        orientation = int(im.getexif().get(274, 1))
                    except Exception:  # noqa: BLE001 - a damaged EXIF block: the decoder decides
                        orientation = 1
            finally:
                Image.MAX_IMAGE_PIXELS = saved
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, struct.error):
        return None
    if width * height > limit:
        raise ImageReadError(f"image file {path} declares {width}x{height} = {width * height:,} pixels, more than "
                             f"the limit of {limit:,} (raise it with --max-image-pixels or {MAX_PIXELS_ENV})")
    if width < 1 or height < 1:
        raise ImageReadError(f"image file {path} declares an empty image ({width}x{height})")
    return ImageHeader(int(width), int(height), orientation if 1 <= orientation <= 8 else 1)



PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")  # the files a folder of photos holds (any case)


def image_files(folder) -> List[str]:
    """The names of the JPEG and PNG files directly in ``folder``, sorted: the images of a folder
    that SfM reconstructs and that posed formats list in name order (LLFF, Bundler)."""
    if not Path(folder).is_dir():
        raise ImageReadError(f"{folder}: the image folder does not exist" if not Path(folder).exists() else
                             f"{folder}: not a folder of images")
    return sorted(p.name for p in Path(folder).iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)


def image_size(path) -> Tuple[int, int]:
    """(width, height) of an image as ``read_image`` decodes it (EXIF orientation applied), from
    its header where PIL reads it, else by decoding it."""
    header = read_header(path)
    if header is not None:
        return header.oriented_size
    height, width = read_image(path).shape[:2]
    return width, height

def _decode_checked(data: bytes, flags: int) -> Tuple[Optional[np.ndarray], str]:
    """cv2.imdecode with the decoder's messages on the C stderr captured: (image, messages).
    An exception of the decoder (cv2.error, memory) is returned as a None image and its words."""
    buffer = np.frombuffer(data, np.uint8)
    error = ""
    with _STDERR_LOCK, tempfile.TemporaryFile() as capture:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(capture.fileno(), 2)
        try:
            image = cv2.imdecode(buffer, flags)
        except (cv2.error, MemoryError, ValueError) as e:
            words = _opencv_words(str(e).strip().splitlines()[-1]) if str(e).strip() else ""
            image, error = None, f"{type(e).__name__}: {words}"
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        messages = capture.read().decode(errors="replace")
    return image, messages + (("\n" + error) if error else "")


def _opencv_words(line: str) -> str:
    """A decoder message without OpenCV's log prefix and source location: "[ERROR:0@0.6] global
    loadsave.cpp:1377 imdecode_ imdecode_(''): can't read header: OpenCV(5.1.0) /io/.../bitstrm.cpp:59:
    error: (-2:Unspecified error) Unexpected end of input stream in function 'readBlock'" reads
    "can't read header: Unexpected end of input stream in function 'readBlock'"."""
    line = re.sub(r"^\[ERROR:[^\]]*\] .*?imdecode_\([^)]*\): ", "", line.strip())
    return re.sub(r"OpenCV\([^)]*\) \S+: error: \([^)]*\) ", "", line)


def _decoded(data: bytes, flags: int) -> Tuple[Optional[np.ndarray], List[str]]:
    """``_decode_checked`` and the decoder's messages that say the data is damaged (a partial decode:
    its missing part would read as zeros); other messages go on to stderr."""
    image, messages = _decode_checked(data, flags)
    problems = [_opencv_words(line) for line in messages.splitlines()
                if any(e in line for e in _DECODER_ERRORS) or "[ERROR:" in line
                or line.startswith(("error:", "MemoryError:", "ValueError:"))]
    other = "".join(line + "\n" for line in messages.splitlines()
                    if line.strip() and "[ERROR:" not in line and _opencv_words(line) not in problems)
    if other:
        sys.stderr.write(other)  # not ours to swallow
    return image, problems


def read_image(path, *, orientation: bool = True) -> np.ndarray:
    """(H, W, 3) uint8 RGB, fully decoded, with the EXIF orientation applied (``orientation``;
    False keeps the pixels as stored). A missing, empty, oversized, truncated or corrupt file
    raises ImageReadError with the file and the decoder's words."""
    return _decode(Path(path), read_header(path), orientation)


def _decode(path: Path, header: Optional[ImageHeader], orientation: bool) -> np.ndarray:
    """The full decode of ``read_image``, once the header (None: unknown to PIL) is checked."""
    flags = cv2.IMREAD_COLOR if orientation else cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ImageReadError(f"image file {path} cannot be read: {e.strerror or e}") from None
    image, problems = _decoded(data, flags)
    if image is None:
        raise ImageReadError(f"image file {path} cannot be decoded" + (f": {problems[0]}" if problems else ""))
    if problems:
        raise ImageReadError(f"image file {path} is truncated or corrupt: {'; '.join(dict.fromkeys(problems))}")
    if header is None and image.shape[0] * image.shape[1] > max_image_pixels():
        raise ImageReadError(f"image file {path} is {image.shape[1]}x{image.shape[0]} pixels, more than the limit "
                             f"of {max_image_pixels():,} (raise it with --max-image-pixels or {MAX_PIXELS_ENV})")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, 2)
    return image[..., ::-1]


def fit_image(camera, size: Tuple[int, int], stored: Optional[Tuple[int, int]] = None):
    """How an image file of ``size`` (width, height, EXIF orientation applied) fits ``camera``
    (a ``CameraRecord``): ``(camera, orientation, note, reason)``.

    The same size: as is. The same aspect ratio: a resized copy, the intrinsics rescaled to the
    file (``note`` says so). Otherwise, where the EXIF orientation swapped the sides and the size
    as ``stored`` fits, the pixels as stored (``orientation`` False: the camera describes them,
    as SfM tools that ignore the tag do). Else ``reason`` says why the image cannot be used."""
    def fits(w, h):
        if (w, h) == (camera.width, camera.height):
            return camera, None
        if abs(w / camera.width - h / camera.height) * max(w, h) <= 1.0:
            return camera.rescaled(w, h), (f"image file is {w}x{h}, the camera says {camera.width}x{camera.height}: "
                                           "intrinsics rescaled to the file")
        return None, None

    cam, note = fits(*size)
    if cam is not None:
        return cam, True, note, None
    if stored is not None and stored != size:
        cam, note = fits(*stored)
        if cam is not None:
            note = "; ".join(filter(None, [f"EXIF orientation ignored: the camera describes the {stored[0]}x"
                                            f"{stored[1]} pixels as stored", note]))
            return cam, False, note, None
    exif = f" (EXIF orientation applied; {stored[0]}x{stored[1]} as stored)" if stored and stored != size else ""
    return camera, True, None, (f"image file is {size[0]}x{size[1]}{exif} but the camera is declared "
                                f"{camera.width}x{camera.height} (another aspect ratio): fix the camera or the file")


def read_image_for(path, camera):
    """The image at ``path`` fitted to ``camera`` (``fit_image``): ``(rgb, camera, note)``; a file
    that cannot be read or does not fit raises ImageReadError naming it. Queries and map images
    both go through here."""
    header = read_header(path)
    if header is not None:
        size, stored = header.oriented_size, (header.width, header.height)
        camera, oriented, note, reason = fit_image(camera, size, stored)
        if reason:
            raise ImageReadError(f"image file {path}: {reason}")
        rgb = _decode(Path(path), header, oriented)
    else:
        rgb = _decode(Path(path), None, True)
        camera, _, note, reason = fit_image(camera, (rgb.shape[1], rgb.shape[0]))
        if reason:
            raise ImageReadError(f"image file {path}: {reason}")
    if (rgb.shape[1], rgb.shape[0]) != (camera.width, camera.height):  # a header that lied
        raise ImageReadError(f"image file {path} decodes to {rgb.shape[1]}x{rgb.shape[0]}, its header says "
                             f"{camera.width}x{camera.height}")
    return rgb, camera, note


def resize_max(image: np.ndarray, max_size: Optional[int]) -> Tuple[np.ndarray, Tuple[float, float]]:
    """Downscale (never upscale) so that the longer side is ``max_size``, as official PixLoc.

    Works on float32 0-255 values with cv2 INTER_LINEAR; the scale is
    max_size / longer side on both axes (official behaviour, not recomputed
    from the rounded size). Returns the image and (sx, sy).
    """
    image = image.astype(np.float32)
    h, w = image.shape[:2]
    if max_size is None or max(h, w) <= max_size:
        return image, (1.0, 1.0)
    scale = max_size / max(h, w)
    size = (int(round(w * scale)), int(round(h * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_LINEAR), (scale, scale)


def to_tensor(image: np.ndarray) -> torch.Tensor:
    """(H, W, 3) 0-255 -> (3, H, W) float32 in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)) / 255.0).float()


def read_depth(path, scale: float) -> np.ndarray:
    """(H, W) float32 depth in scene units; 0 where invalid (0 or 65535 in 16-bit files)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ImageReadError(f"depth file {path} cannot be read: {e.strerror or e}") from None
    depth, problems = _decoded(data, cv2.IMREAD_UNCHANGED) if data else (None, ["the file is empty"])
    if depth is None:
        raise ImageReadError(f"depth file {path} cannot be decoded" + (f": {problems[0]}" if problems else ""))
    if problems:  # decoded in part: the rest would read as zero depth
        raise ImageReadError(f"depth file {path} is truncated or corrupt: {'; '.join(dict.fromkeys(problems))}")
    if depth.ndim != 2:
        raise ImageReadError(f"depth file {path} has {depth.shape[2]} channels, not one")
    invalid = (depth == 0) | (depth == 65535) if depth.dtype == np.uint16 else ~np.isfinite(depth)
    depth = depth.astype(np.float32) * scale
    depth[invalid] = 0
    return depth


def file_sha256(path) -> str:
    """The SHA-256 (hex) of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
