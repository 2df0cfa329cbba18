"""Image reading and resizing, as official PixLoc does them (OpenCV), and file digests."""

import hashlib
import os
import sys
import tempfile
import threading
from pathlib import Path
from typing import Optional, Tuple

import cv2
import numpy as np
import torch


class ImageReadError(IOError):
    """An image file that is missing or cannot be decoded."""


# What libjpeg and libpng print (they do not fail) when a file is truncated or corrupt: OpenCV
# then returns a partly grey image as if nothing happened.
_DECODER_ERRORS = ("Corrupt JPEG data", "Premature end of JPEG file", "JPEG datastream contains no image",
                   "libpng error", "Invalid SOS parameters", "Bogus marker length", "Huffman")
_STDERR_LOCK = threading.Lock()


def _decode_checked(data: bytes) -> Tuple[Optional[np.ndarray], str]:
    """cv2.imdecode with the decoder's messages on the C stderr captured: (image, messages)."""
    buffer = np.frombuffer(data, np.uint8)
    with _STDERR_LOCK, tempfile.TemporaryFile() as capture:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(capture.fileno(), 2)
        try:
            image = cv2.imdecode(buffer, cv2.IMREAD_COLOR)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        messages = capture.read().decode(errors="replace")
    return image, messages


def read_image(path) -> np.ndarray:
    """(H, W, 3) uint8 RGB, fully decoded; a missing, truncated or corrupt file raises
    ImageReadError with the decoder's words."""
    path = Path(path)
    if not path.is_file():
        raise ImageReadError(f"image file {path} is missing")
    image, messages = _decode_checked(path.read_bytes())
    problems = [line.strip() for line in messages.splitlines() if any(e in line for e in _DECODER_ERRORS)]
    other = "".join(line + "\n" for line in messages.splitlines() if line.strip() and line.strip() not in problems)
    if other:
        sys.stderr.write(other)  # not ours to swallow
    if image is None:
        raise ImageReadError(f"image file {path} cannot be decoded" + (f": {problems[0]}" if problems else ""))
    if problems:
        raise ImageReadError(f"image file {path} is truncated or corrupt: {'; '.join(dict.fromkeys(problems))}")
    return image[..., ::-1]


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
    depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if depth is None:
        raise ImageReadError(f"depth file {path} is missing or cannot be decoded")
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
