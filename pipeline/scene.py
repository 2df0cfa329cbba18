"""Typed records of a 3D map before features: cameras, posed images, points, observations."""

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

from pixloc.geometry import COLMAP_MODELS, Camera, Pose, lie
from pixloc.geometry.camera import NUM_COLMAP_PARAMS


def qvec_to_rotmat(qvec) -> np.ndarray:
    """(3, 3) rotation from a quaternion (w, x, y, z), normalised here (pixloc's conversion)."""
    return lie.qvec_to_rotmat(torch.as_tensor(np.asarray(qvec, np.float64))).numpy()


def rotmat_to_qvec(R) -> np.ndarray:
    """(w, x, y, z), w >= 0, of a (3, 3) rotation (pixloc's conversion)."""
    return lie.rotmat_to_qvec(torch.as_tensor(np.asarray(R, np.float64))).numpy()


MAX_SIDE = 100_000  # pixels
MIN_FOCAL_FACTOR, MAX_FOCAL_FACTOR = 0.004, 100.0  # x the longer side: about 179 to 0.6 deg across it


def name_problem(name: str) -> Optional[str]:
    """Why ``name`` cannot name an image, or None. Names are relative paths inside their image
    folder (as COLMAP and kapture write them): not empty, not absolute, no ``..``, no control
    characters, so that a name never reads a file outside its folder."""
    if not name or not name.strip():
        return "empty image name"
    if any(ord(c) < 32 for c in name):
        return f"image name {name!r} has control characters"
    p = name.replace("\\", "/")
    if p.startswith("/") or (len(p) > 1 and p[1] == ":"):
        return f"image name {name!r} is absolute: names are relative to the image folder"
    if ".." in p.split("/"):
        return f"image name {name!r} leaves the image folder ('..'): names are relative paths inside it"
    return None


class SceneError(ValueError):
    """Input that cannot make a map (empty model, unsupported camera, NaN pose...)."""


@dataclass(frozen=True)
class CameraRecord:
    """A COLMAP camera: model name, image size in pixels, params in COLMAP's convention."""

    model: str
    width: int
    height: int
    params: tuple

    def check(self) -> Optional[str]:
        """None if usable, else why not. Every camera is checked where it is read (query lists,
        models, store): a supported model with its parameter count, finite parameters, a size of
        1 to ``MAX_SIDE`` pixels a side, focal lengths that give a field of view between about
        0.6 and 179 degrees (``MIN_FOCAL_FACTOR`` to ``MAX_FOCAL_FACTOR`` x the longer side; zero
        or negative focal lengths are refused), and a principal point within half an image of
        the image."""
        if self.model not in COLMAP_MODELS:
            return f"unsupported camera model {self.model!r} (supported: {', '.join(COLMAP_MODELS)})"
        if len(self.params) != NUM_COLMAP_PARAMS[self.model]:
            return (f"camera model {self.model} has {NUM_COLMAP_PARAMS[self.model]} parameters, "
                    f"got {len(self.params)}")
        w, h = self.width, self.height
        try:
            whole = int(w) == w and int(h) == h
        except (TypeError, ValueError, OverflowError):
            whole = False
        if not whole or not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
            return f"camera {self.model} has an invalid size {w}x{h} (1 to {MAX_SIDE} pixels a side)"
        if not all(math.isfinite(p) for p in self.params):
            return f"camera {self.model} {w}x{h} has non-finite parameters {list(self.params)}"
        focals, (cx, cy) = self.focals(), self.principal_point()
        side = max(w, h)
        for f in focals:
            if not MIN_FOCAL_FACTOR * side <= f <= MAX_FOCAL_FACTOR * side:
                return (f"camera {self.model} {w}x{h} has focal length {f:g} px: it must be positive, between "
                        f"{MIN_FOCAL_FACTOR:g} and {MAX_FOCAL_FACTOR:g} x the longer side")
        if not (-0.5 * w <= cx <= 1.5 * w and -0.5 * h <= cy <= 1.5 * h):
            return f"camera {self.model} {w}x{h} has its principal point ({cx:g}, {cy:g}) far outside the image"
        return None

    def focals(self) -> tuple:
        """(f,) or (fx, fy) in pixels, by the COLMAP model's parameter order."""
        return tuple(self.params[:1] if self._single_focal() else self.params[:2])

    def principal_point(self) -> tuple:
        """(cx, cy), COLMAP pixel convention."""
        return tuple(self.params[1:3] if self._single_focal() else self.params[2:4])

    def _single_focal(self) -> bool:
        return self.model.startswith("SIMPLE") or self.model == "RADIAL"

    def rescaled(self, width: int, height: int) -> "CameraRecord":
        """The same camera for an image of ``width`` x ``height`` (a resized copy of the file)."""
        sx, sy = width / self.width, height / self.height
        p = list(self.params)
        if self._single_focal():
            p[:3] = [p[0] * sx, p[1] * sx, p[2] * sy]
        else:
            p[:4] = [p[0] * sx, p[1] * sy, p[2] * sx, p[3] * sy]
        return CameraRecord(self.model, int(width), int(height), tuple(p))

    def to_pixloc(self, dtype=torch.float32) -> Camera:
        return Camera.from_colmap(self.model, self.width, self.height, self.params, dtype=dtype)

    def to_json(self) -> str:
        return json.dumps([self.model, self.width, self.height, list(self.params)])

    @classmethod
    def from_json(cls, s: str) -> "CameraRecord":
        model, w, h, params = json.loads(s)
        return cls(model, int(w), int(h), tuple(params))


@dataclass
class ImageRecord:
    """A reference image: its file, camera and cam_from_world pose ((3, 4) [R | t], float64).

    tags: condition tags (day/night, season, sequence...). depth: an optional
    depth map file, the factor that turns its values into scene units, the
    camera of the depth map when it is not registered to the image (other
    intrinsics: 7-Scenes) and ``color_from_depth``, the rigid transform (3, 4)
    from the depth sensor's frame to the image's where the two sensors are apart
    (None: depth is taken at the image's pose). ``cam_from_world`` is always the
    image's own pose: the one projected with, estimated and evaluated. ``problem``: set by
    a reader that found the image unusable (``check`` returns it: the build records the
    image as failed with it).
    """

    name: str
    path: Path
    camera: CameraRecord
    cam_from_world: np.ndarray
    tags: Dict[str, str] = field(default_factory=dict)
    depth_path: Optional[Path] = None
    depth_scale: float = 1.0
    depth_camera: Optional[CameraRecord] = None
    source_id: int = -1  # the image's id in its source model (COLMAP image_id), -1 if none
    color_from_depth: Optional[np.ndarray] = None
    problem: Optional[str] = None  # why a reader found it unusable (its depth file cannot be read): it fails
    origin: str = ""  # where its reader found it ("file:line", "file: frame 3"), for messages

    def check(self) -> Optional[str]:
        reason = self.problem or name_problem(self.name) or self.camera.check()
        if reason:
            return reason
        T = np.asarray(self.cam_from_world)
        if T.shape != (3, 4) or not np.isfinite(T).all():
            return "pose is not a finite 3x4 matrix"
        R = T[:, :3]
        if abs(np.linalg.det(R) - 1) > 1e-3 or not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
            return "pose rotation is not a rotation matrix"
        return None

    def pose(self, dtype=torch.float32) -> Pose:
        return Pose.from_matrix(self.cam_from_world, dtype)

    def depth_from_world(self) -> np.ndarray:
        """The depth sensor's pose (3, 4): back-projection, fusion and depth tests use it."""
        if self.color_from_depth is None:
            return np.asarray(self.cam_from_world, np.float64)
        return (Pose.from_matrix(self.color_from_depth).inv() @ Pose.from_matrix(self.cam_from_world)).to_matrix()


def refuse_duplicates(images: Sequence["ImageRecord"], source) -> None:
    """Each image name once, or SceneError naming the repeated one where its reader found it
    (``ImageRecord.origin``, else ``source``) and where it came first: a map cannot hold one image
    twice, and COLMAP's database aborts the process on a second one ("constraint failed")."""
    first: Dict[str, "ImageRecord"] = {}
    for im in images:
        if im.name in first:
            before = first[im.name].origin
            raise SceneError(f"{im.origin or source}: image {im.name} is listed twice"
                             f"{f' (first at {before})' if before else ''}: each image once.")
        first[im.name] = im


@dataclass
class Scene:
    """A sparse 3D map: images, points (P, 3) in the world frame, and their observations.

    Observation k says that point ``obs_point[k]`` is seen in image
    ``obs_image[k]`` at ``obs_xy[k]`` (COLMAP pixel coordinates, origin at
    the top-left corner; NaN where unknown, e.g. points sampled from depth).
    ``point_ids``: each point's id in its source model (COLMAP point3D_id), -1 if none;
    they let another pipeline's logs (hloc PnP inliers) name the map's points.
    """

    images: List[ImageRecord]
    points: np.ndarray
    obs_point: np.ndarray
    obs_image: np.ndarray
    obs_xy: np.ndarray
    point_ids: Optional[np.ndarray] = None

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        self.point_ids = (np.full(len(self.points), -1, dtype=np.int64) if self.point_ids is None
                          else np.asarray(self.point_ids, dtype=np.int64).reshape(-1))
        if len(self.point_ids) != len(self.points):
            raise SceneError("point_ids and points have different lengths.")
        self.obs_point = np.asarray(self.obs_point, dtype=np.int64).reshape(-1)
        self.obs_image = np.asarray(self.obs_image, dtype=np.int64).reshape(-1)
        self.obs_xy = np.asarray(self.obs_xy, dtype=np.float64).reshape(-1, 2)
        n = len(self.obs_point)
        if len(self.obs_image) != n or len(self.obs_xy) != n:
            raise SceneError("Observation arrays have different lengths.")
        if n and (self.obs_point.min() < 0 or self.obs_point.max() >= len(self.points)):
            raise SceneError("Observations reference points that do not exist.")
        if n and (self.obs_image.min() < 0 or self.obs_image.max() >= len(self.images)):
            raise SceneError("Observations reference images that do not exist.")
        refuse_duplicates(self.images, "the map")

    @property
    def track_length(self) -> np.ndarray:
        """(P,) number of images observing each point."""
        return np.bincount(self.obs_point, minlength=len(self.points))

    def check(self) -> Dict[int, str]:
        """Problems per image index; raises for a scene that cannot make a map at all."""
        if not self.images:
            raise SceneError("The model has no images.")
        if len(self.points) == 0:
            raise SceneError("The model has no 3D points.")
        if not np.isfinite(self.points).all():
            raise SceneError(f"{int((~np.isfinite(self.points).all(1)).sum())} 3D points are not finite.")
        problems = {i: r for i, im in enumerate(self.images) if (r := im.check())}
        for i, im in enumerate(self.images):
            if i not in problems and not Path(im.path).is_file():
                problems[i] = f"image file {im.path} is missing"
        return problems

    def repeated(self, times: int) -> "Scene":
        """The scene with its images repeated ``times`` under new names ``k/name``
        (same files and points): a larger map for benchmarks and parallel tests."""
        images = [dataclasses.replace(im, name=f"{k}/{im.name}") for k in range(times) for im in self.images]
        obs_image = np.concatenate([self.obs_image + k * len(self.images) for k in range(times)])
        return Scene(images, self.points, np.tile(self.obs_point, times), obs_image, np.tile(self.obs_xy, (times, 1)),
                     self.point_ids)

    def subset(self, keep: Sequence[int]) -> "Scene":
        """The scene restricted to images ``keep`` (their observations, all points)."""
        keep = np.asarray(keep, dtype=np.int64)
        remap = -np.ones(len(self.images), dtype=np.int64)
        remap[keep] = np.arange(len(keep))
        sel = remap[self.obs_image] >= 0
        return Scene([self.images[i] for i in keep], self.points, self.obs_point[sel],
                     remap[self.obs_image[sel]], self.obs_xy[sel], self.point_ids)
