"""A classical pose that PixLoc refines: SIFT features of the query matched to those of its
retrieved references, the matched reference keypoints that lie on the map's observations give
2D-3D correspondences, and pycolmap's absolute pose (LO-RANSAC, then refinement, the query's
camera) gives the pose. The PixLoc paper positions the method as the refiner of such poses.

Reference descriptors come from the map where it stores them (``build-map --sift``: one per
observation), else from the map's images when a query first needs them, kept for the process
(``reference_sift``). A pose needs ``min_inliers``
PnP inliers; where PnP fails, ``pipeline.localization.priors`` falls back to the search prior.
"""

import functools
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from pipeline.images import ImageReadError, read_image
from pipeline.localization.candidates import Keypoints
from pipeline.keypoints import MAX_FEATURES, MAX_GAP, extract_sift, from_uint8, nearest_within
from pipeline.scene import CameraRecord
from pixloc.optim.keypoints import residual_scale
from pipeline.store.reader import MapReader


@dataclass(frozen=True)
class SiftConfig:
    """max_size: longer image side for extraction (pixels); max_features: per image; ratio:
    Lowe's ratio test of mutual nearest neighbours; max_gap: pixels between a matched reference
    keypoint and the map observation it stands for; max_error: RANSAC inlier threshold (pixels);
    min_inliers: PnP inliers a pose needs (10: the official code's threshold for hloc's PnP poses; 20
    left 4 of dino's 48 queries, right with 11 to 18 inliers of 12 to 21, to the search prior);
    levels: the levels a PnP pose is refined on, the two finest as the official code refines hloc's
    PnP poses (``layer_indices``): from a pose this close the coarsest level only moves it away (on
    the photo city it took 3 of 24 accepted poses 0.4 to 1.3 m off). The search fallback runs every level."""

    max_size: int = 1600
    max_features: int = MAX_FEATURES
    ratio: float = 0.85
    max_gap: float = MAX_GAP
    max_error: float = 8.0
    min_inliers: int = 10
    levels: Tuple[int, ...] = (0, 1)

    def validate(self) -> None:
        if self.max_size < 64 or self.max_features < 8 or not 0 < self.ratio <= 1 or self.min_inliers < 4 \
                or 0 not in self.levels or min(self.levels) < 0:
            raise ValueError(f"SIFT settings out of range: {self} (levels must hold 0, the finest).")


@dataclass
class PnPResult:
    """The pose (cam_from_world, 3 x 4) or None, and the evidence: correspondences, inliers,
    matches per reference; where a pose was found, its inliers (``keypoints``: their query keypoints in
    COLMAP pixels, map points and residual scale)."""

    pose: Optional[np.ndarray]
    correspondences: int
    inliers: int
    matches: List[int]
    unreadable: List[str] = field(default_factory=list)  # references whose image could not be read, and why
    keypoints: Optional[Keypoints] = None

    def describe(self) -> str:
        """The note a query's record carries (ending in ``FALLBACK`` where the search took over)."""
        missing = (f"; no SIFT from {len(self.unreadable)} reference(s) without descriptors in the map, whose "
                   f"image cannot be read ({'; '.join(self.unreadable[:2])}): build-map --sift stores them"
                   if self.unreadable else "")
        return (f"{NOTE}{self.inliers} inliers of {self.correspondences} 2D-3D matches "
                f"(matches per reference {self.matches}{missing})")


NOTE = "SIFT PnP: "  # how a record's note starts that says what SIFT + PnP found
FALLBACK = "the search prior instead"  # ... and how it ends where PnP failed


def pnp_pose_found(notes) -> bool:
    """Whether a record's notes say that its prior is a SIFT + PnP pose."""
    return any(n.startswith(NOTE) and not n.endswith(FALLBACK) for n in notes)


def extract(rgb: np.ndarray, conf: SiftConfig) -> Tuple[np.ndarray, np.ndarray]:
    """Keypoints (N, 2) in COLMAP pixel coordinates of ``rgb`` and L2-normalised descriptors (N, 128)."""
    return extract_sift(rgb, conf.max_size, conf.max_features)


@functools.lru_cache(maxsize=256)
def reference_sift(path: str, width: int, height: int, conf: SiftConfig) -> Tuple[np.ndarray, np.ndarray]:
    """A map image's SIFT, in the pixel coordinates of its camera (width x height), once per process."""
    rgb = read_image(path)
    xy, d = extract(rgb, conf)
    return xy * np.array([width / rgb.shape[1], height / rgb.shape[0]]), d


def mutual_matches(a: np.ndarray, b: np.ndarray, ratio: float) -> np.ndarray:
    """(K, 2) indices of mutual nearest neighbours between descriptor sets that pass the ratio test."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    sim = a @ b.T
    order = np.argsort(-sim, axis=1)[:, :2]
    best, second = order[:, 0], order[:, 1]
    dist = np.sqrt(np.maximum(2 - 2 * sim[np.arange(len(a)), best], 0))
    dist2 = np.sqrt(np.maximum(2 - 2 * sim[np.arange(len(a)), second], 0))
    back = np.argmax(sim, axis=0)
    keep = (back[best] == np.arange(len(a))) & (dist < ratio * dist2)
    return np.stack([np.flatnonzero(keep), best[keep]], 1)


def reference_matches(reader: MapReader, i: int, q_desc: np.ndarray, conf: SiftConfig) -> np.ndarray:
    """(K, 2): query keypoint, map point, for the query's SIFT matches to reference i that land on
    its observations. Where the map stores descriptors (``build-map --sift``: one per observation),
    the query is matched to those; else to the reference image's SIFT (``reference_sift``), and a
    matched keypoint stands for the observation within ``max_gap`` pixels of it."""
    obs_point = reader.image_points(i)
    stored = reader.sift_descriptors(i)
    if stored is not None:
        rows = np.flatnonzero(stored.any(1) & (obs_point >= 0))
        pairs = mutual_matches(q_desc, from_uint8(stored[rows]), conf.ratio)
        return np.stack([pairs[:, 0], obs_point[rows[pairs[:, 1]]]], 1)
    camera = reader.cameras[i]
    r_xy, r_desc = reference_sift(str(reader.image_path(i)), camera.width, camera.height, conf)
    pairs = mutual_matches(q_desc, r_desc, conf.ratio)
    obs_xy = reader.image_xy(i)
    rows = np.flatnonzero(np.isfinite(obs_xy).all(1) & (obs_point >= 0))
    hit = nearest_within(r_xy[pairs[:, 1]], obs_xy[rows], conf.max_gap) if len(pairs) else np.zeros(0, np.int64)
    return np.stack([pairs[hit >= 0, 0], obs_point[rows[hit[hit >= 0]]]], 1).astype(np.int64)


def sift_pnp(reader: MapReader, dbs: List[int], rgb: np.ndarray, camera: CameraRecord,
             conf: SiftConfig) -> PnPResult:
    """The query's pose from SIFT matches to the references ``dbs`` that land on map observations."""
    import pycolmap

    q_xy, q_desc = extract(rgb, conf)
    point_of: Dict[int, int] = {}  # query keypoint -> map point (the first reference's wins)
    per_ref, unreadable = [], []
    for i in dbs:
        found = 0
        try:
            matched = reference_matches(reader, i, q_desc, conf)
        except ImageReadError as e:  # a map moved without its images: the other references still match
            matched = np.zeros((0, 2), np.int64)
            unreadable.append(str(e))
        for k, point in matched:
            if k not in point_of:
                point_of[int(k)] = int(point)
                found += 1
        per_ref.append(found)
    keys = sorted(point_of)
    if len(keys) < max(conf.min_inliers, 4):
        return PnPResult(None, len(keys), 0, per_ref, unreadable)
    p2d = q_xy[keys]
    p3d = reader.xyz[[point_of[k] for k in keys]]
    cam = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height, params=list(camera.params))
    options = pycolmap.AbsolutePoseEstimationOptions()
    options.ransac.max_error = conf.max_error
    options.ransac.random_seed = 0
    found = pycolmap.estimate_and_refine_absolute_pose(p2d, p3d, cam, options)
    if found is None:
        return PnPResult(None, len(keys), 0, per_ref, unreadable)
    inliers = int(found["num_inliers"])
    pose = np.asarray(found["cam_from_world"].matrix(), np.float64)
    if inliers < conf.min_inliers:
        return PnPResult(None, len(keys), inliers, per_ref, unreadable)
    mask = np.asarray(found["inlier_mask"], bool)
    xy, xyz = p2d[mask], p3d[mask]
    projected = cam.img_from_cam(xyz @ pose[:, :3].T + pose[:, 3])
    return PnPResult(pose, len(keys), inliers, per_ref, unreadable,
                     Keypoints(xy, xyz, residual_scale(xy, projected)))
