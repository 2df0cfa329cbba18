"""COLMAP model folders, opened only after their binary files are checked whole, and text models
checked against the counts their headers name.

pycolmap reads a binary model without checking that each record fits in its file: a truncated
``points3D.bin`` or ``frames.bin`` makes it loop on a failed stream (pycolmap 4.2: more than 8 GB
in 20 s, or a hang). ``check_binary_model`` walks every record's size, in the layout of COLMAP's
``reconstruction_io_binary`` (little endian), and names the file and the record that does not fit.
"""

import codecs
import contextlib
import re
import shutil
import struct
import tempfile
from functools import lru_cache
from pathlib import Path

import pycolmap

from pipeline.scene import SceneError


@lru_cache(maxsize=None)
def _num_params(model_id: int) -> int:
    """The number of parameters of COLMAP camera model ``model_id``; -1 for an unknown model."""
    try:  # an id that the enum takes may still name no model: pycolmap's Check fails
        return len(pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId(model_id), 1.0, 1, 1).params)
    except (ValueError, RuntimeError):
        return -1


class _Walk:
    """A cursor over one file's bytes; ``take`` reads ``fmt`` or raises naming the record."""

    def __init__(self, path: Path):
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def take(self, fmt: str, what: str):
        size = struct.calcsize("<" + fmt)
        if self.at + size > len(self.data):
            raise SceneError(f"{self.path}: {what} runs past the end of the file ({len(self.data)} bytes): "
                             "the file is truncated or damaged.")
        values = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += size
        return values

    def skip(self, size: int, what: str) -> None:
        if self.at + size > len(self.data):
            raise SceneError(f"{self.path}: {what} runs past the end of the file ({len(self.data)} bytes): "
                             "the file is truncated or damaged.")
        self.at += size

    def count(self, fmt: str, least: int, what: str) -> int:
        """A record count, refused at once where even records of ``least`` bytes could not fit (a
        count inside a record needs no such check: ``take`` and ``skip`` stop at the file's end)."""
        (n,) = self.take(fmt, f"the number of {what}")
        if n * least > len(self.data) - self.at:
            raise SceneError(f"{self.path}: it says {n} {what}, more than its {len(self.data)} bytes can hold: "
                             "the file is truncated or damaged.")
        return n

    def end(self) -> None:
        if self.at != len(self.data):
            raise SceneError(f"{self.path}: {len(self.data) - self.at} bytes after its last record: "
                             "the file is damaged.")


def _cameras(w: _Walk) -> None:
    for k in range(w.count("Q", 24, "cameras")):
        camera_id, model_id, _, _ = w.take("IiQQ", f"camera {k}")
        n = _num_params(model_id)
        if n < 0:
            raise SceneError(f"{w.path}: camera {camera_id} has the unknown camera model id {model_id}.")
        w.skip(8 * n, f"camera {camera_id}'s parameters")


def _images(w: _Walk) -> None:
    for k in range(w.count("Q", 73, "images")):
        (image_id,) = w.take("I56xI", f"image {k}")[:1]
        end = w.data.find(b"\0", w.at)
        if end < 0:
            raise SceneError(f"{w.path}: image {image_id}'s name runs past the end of the file: "
                             "the file is truncated or damaged.")
        w.at = end + 1
        n = w.count("Q", 24, f"2D points of image {image_id}")
        w.skip(24 * n, f"image {image_id}'s 2D points")


def _points(w: _Walk) -> None:
    for k in range(w.count("Q", 51, "3D points")):
        point_id, track = w.take("Q24x3B8xQ", f"3D point {k}")[0::4]
        w.skip(8 * track, f"3D point {point_id}'s track")


def _rigs(w: _Walk) -> None:
    for k in range(w.count("Q", 8, "rigs")):
        rig_id, sensors = w.take("II", f"rig {k}")
        if sensors:
            w.take("iI", f"rig {rig_id}'s reference sensor")
        for _ in range(max(sensors - 1, 0)):
            (has_pose,) = w.take("iIB", f"a sensor of rig {rig_id}")[2:]
            if has_pose:
                w.skip(56, f"a sensor pose of rig {rig_id}")


def _frames(w: _Walk) -> None:
    for k in range(w.count("Q", 68, "frames")):
        frame_id, _, n = w.take("II56xI", f"frame {k}")
        w.skip(16 * n, f"frame {frame_id}'s data ids")


FILES = {"rigs.bin": _rigs, "cameras.bin": _cameras, "frames.bin": _frames, "images.bin": _images,
         "points3D.bin": _points}


def check_binary_model(model_dir: Path) -> None:
    """SceneError naming the file and record where a binary model's records do not fill its files exactly."""
    for name, walk in FILES.items():
        path = Path(model_dir) / name
        if path.is_file():
            w = _Walk(path)
            walk(w)
            w.end()


# a text model's header comment: how many records COLMAP wrote, against what pycolmap read back
TEXT_COUNTS = {"rigs.txt": ("rigs", "num_rigs"), "cameras.txt": ("cameras", "num_cameras"),
               "frames.txt": ("frames", "num_frames"), "images.txt": ("images", "num_images"),
               "points3D.txt": ("points", "num_points3D")}


def check_text_counts(model_dir: Path, rec: pycolmap.Reconstruction) -> None:
    """SceneError where a text model holds fewer records than its header comment says: a file cut at a
    line end reads without an error, and would silently drop the rest."""
    for name, (what, count) in TEXT_COUNTS.items():
        path = Path(model_dir) / name
        if not path.is_file() or (Path(model_dir) / name.replace(".txt", ".bin")).is_file():
            continue
        with open(path, "rb") as f:
            head = b"".join(f.readline() for _ in range(5)).decode("utf-8", "replace")
        found = re.search(rf"^# Number of {what}: (\d+)", head, re.MULTILINE)
        if found and getattr(rec, count)() < int(found.group(1)):
            raise SceneError(f"{path}: it holds {getattr(rec, count)()} {what} of the {found.group(1)} its header "
                             "names: the file is truncated.")


def read_reconstruction(model_dir) -> pycolmap.Reconstruction:
    """The COLMAP model in ``model_dir`` (binary or text); a damaged binary file is refused, named,
    before pycolmap reads it; pycolmap's own errors become SceneErrors naming the folder."""
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise SceneError(f"COLMAP model folder {model_dir} does not exist.")
    check_binary_model(model_dir)
    with _without_byte_order_marks(model_dir) as readable:
        try:
            rec = pycolmap.Reconstruction(str(readable))
        except Exception as e:  # pycolmap raises plain RuntimeErrors/ValueErrors
            raise SceneError(f"Cannot read the COLMAP model in {model_dir}: {e}") from None
    check_text_counts(model_dir, rec)
    return rec


@contextlib.contextmanager
def _without_byte_order_marks(model_dir: Path):
    """``model_dir``, or, where one of its text files starts with a byte-order mark (what Notepad
    writes, and pycolmap fails on), a temporary copy of its text files without it."""
    texts = [name for name in TEXT_COUNTS if (model_dir / name).is_file()
             and not (model_dir / name.replace(".txt", ".bin")).is_file()]
    marked = []
    for name in texts:
        with open(model_dir / name, "rb") as f:
            if f.read(3) == codecs.BOM_UTF8:
                marked.append(name)
    if not marked:
        yield model_dir
        return
    with tempfile.TemporaryDirectory(prefix="pixloc-colmap-") as tmp:
        for name in texts:
            with open(model_dir / name, "rb") as src, open(Path(tmp) / name, "wb") as dst:
                if name in marked:
                    src.read(3)
                shutil.copyfileobj(src, dst)
        yield Path(tmp)
