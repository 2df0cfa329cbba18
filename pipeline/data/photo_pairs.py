"""Self-supervised training pairs from any photo, posed or not: the photo is a plane seen by a
reference camera, and a second camera at a known pose sees the same plane, so the relative pose and
every correspondence are exact. The second view is the photo warped by the plane's homography, then
changed as night changes a place (darker, warmer, noisy, lit by lamps, blurred, JPEG-compressed) and
partly hidden by occluders. Many more real textures per CPU hour than rendering.

Geometry, in the reference camera's frame: the plane ``n . X = d`` (``d`` = 1, ``n`` tilted up to
``max_tilt`` from the optical axis); the query camera looks at the plane's centre from a point off the
axis, turned and rolled a little. A reference pixel ``p`` maps to the query at ``K_q (R + t n^T / d)
K_ref^-1 p``. Pixel coordinates are those of ``pixloc.geometry.Camera`` (pixel centres at integers).
"""

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import List, Sequence, Tuple

import cv2
import numpy as np
import torch

from pixloc.geometry import Camera, Pose
from pixloc.refiner import PairBatch

from pipeline.images import ImageReadError, read_image
from pipeline.data.training_data import PairConfig, draw_init_fraction, initial_pose

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PhotoPairConfig:
    """max_tilt: the plane's largest angle to the optical axis (deg). baseline: the query camera's
    distance off the reference's centre, in plane distances. turn, roll: the query's extra rotation
    (deg) after looking at the plane's centre. focal_ratio: the query focal over the reference's.
    night: the share of queries changed as at night (the others by day: exposure, colour, noise).
    occluders: the share of queries with 1-3 occluders."""

    max_tilt: float = 40.0
    baseline: Tuple[float, float] = (0.2, 0.9)
    turn: float = 10.0
    roll: float = 15.0
    focal_ratio: Tuple[float, float] = (0.8, 1.25)
    night: float = 0.5
    occluders: float = 0.5


def _scaled(image: np.ndarray, max_side: int) -> np.ndarray:
    scale = min(1.0, max_side / max(image.shape[:2]))
    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else image


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, np.float64) * angle)[0]


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World-to-camera rotation of a camera at ``centre`` looking at ``target``, y down."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _intrinsics(f: float, width: int, height: int) -> np.ndarray:
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])


def day_change(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Exposure, contrast, white balance and noise of another time of day (float32 0-1 in and out)."""
    out = image ** rng.uniform(0.7, 1.4) * rng.uniform(0.7, 1.2)
    out = (out - out.mean()) * rng.uniform(0.8, 1.2) + out.mean()
    out = out * rng.uniform(0.9, 1.1, size=3)
    return np.clip(out + rng.normal(0, rng.uniform(0, 0.015), out.shape), 0, 1).astype(np.float32)


def night_change(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The photo as at night: darker by a gamma, warmer (sodium light), lit by a few lamps, blurred,
    noisy and JPEG-compressed (float32 0-1 in and out)."""
    h, w = image.shape[:2]
    out = image ** rng.uniform(1.6, 3.0) * rng.uniform(0.5, 0.9)
    warm = rng.uniform(0.0, 0.4)
    out = out * np.array([1 + warm, 1 + warm / 3, 1 - warm])
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    for _ in range(int(rng.integers(0, 5))):
        x, y, s = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0.03, 0.2) * max(h, w)
        glow = np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * s * s))[..., None]
        out = out + glow * rng.uniform(0.2, 0.8) * np.array([1.0, rng.uniform(0.6, 0.9), rng.uniform(0.2, 0.6)])
    sigma = rng.uniform(0, 1.5)
    if sigma > 0.3:
        out = cv2.GaussianBlur(out.astype(np.float32), (0, 0), sigma)
    out = np.clip(out + rng.normal(0, rng.uniform(0.01, 0.05), out.shape), 0, 1)
    ok, jpeg = cv2.imencode(".jpg", (out * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(20, 70))])
    return (cv2.imdecode(jpeg, cv2.IMREAD_UNCHANGED) / 255.0).astype(np.float32)


def occlude(image: np.ndarray, rng: np.random.Generator, other: np.ndarray) -> np.ndarray:
    """1-3 rectangles or ellipses, each 3-15 % of the image, filled with a colour or with a patch of
    ``other`` (another photo)."""
    h, w = image.shape[:2]
    out = image.copy()
    for _ in range(int(rng.integers(1, 4))):
        area = rng.uniform(0.03, 0.15) * h * w
        aspect = rng.uniform(0.3, 3)
        bw, bh = int(min(w, np.sqrt(area * aspect))), int(min(h, np.sqrt(area / aspect)))
        x, y = int(rng.integers(0, w - bw + 1)), int(rng.integers(0, h - bh + 1))
        mask = np.zeros((h, w), np.uint8)
        if rng.uniform() < 0.5:
            mask[y:y + bh, x:x + bw] = 1
        else:
            cv2.ellipse(mask, (x + bw // 2, y + bh // 2), (max(1, bw // 2), max(1, bh // 2)), 0, 0, 360, 1, -1)
        if rng.uniform() < 0.5:
            fill = np.broadcast_to(rng.uniform(0, 1, 3), out.shape)
        else:
            fill = cv2.resize(other, (w, h), interpolation=cv2.INTER_AREA)
        out[mask > 0] = fill[mask > 0]
    return out


class PhotoPairs:
    """Pairs of one set of photos (the interface of ``PairDataset``: ``sample``, ``fixed``, ``pair``).
    Photos are read once, at twice the training size; each pair draws its photo, plane, cameras,
    changes and points from the generator it is given."""

    def __init__(self, photos: Sequence[Path], conf: PairConfig = PairConfig(),
                 photo_conf: PhotoPairConfig = PhotoPairConfig()):
        """Every photo is read here, once: one that cannot be read is left out with a warning that
        names it (``unreadable``), and a source with none left is refused."""
        self.conf, self.photo_conf = conf, photo_conf
        self._images: List[np.ndarray] = []  # 8-bit RGB, longer side at most twice the training size
        self.photos: List[Path] = []
        self.unreadable: List[str] = []
        for path in map(Path, photos):
            try:
                image = _scaled(read_image(path), 2 * conf.max_size)
            except ImageReadError as e:
                self.unreadable.append(str(e))
                continue
            self._images.append(image)
            self.photos.append(path)
        if self.unreadable:
            logger.warning("%d photos left out: %s", len(self.unreadable), "; ".join(self.unreadable[:5]))
        if not self.photos:
            raise ValueError("A photos training source needs at least one readable photo"
                             + (f" ({self.unreadable[0]})." if self.unreadable else "."))

    def __len__(self) -> int:
        return len(self.photos)

    def photo(self, i: int) -> np.ndarray:
        """Photo ``i`` as float32 0-1 RGB, longer side at most twice the training size (kept as 8 bits)."""
        return self._images[i].astype(np.float32) / 255.0

    def _cameras(self, rng: np.random.Generator, size: Tuple[int, int]):
        """The plane (n, d), the reference and query intrinsics, and the query's pose (R, t)."""
        c = self.photo_conf
        w, h = size
        tilt = np.deg2rad(rng.uniform(0, c.max_tilt))
        azimuth = rng.uniform(0, 2 * np.pi)
        n = _rotation([np.cos(azimuth), np.sin(azimuth), 0], tilt) @ np.array([0, 0, 1.0])
        d = 1.0
        f_ref = max(w, h) * rng.uniform(0.7, 1.2)
        K_ref = _intrinsics(f_ref, w, h)
        K_q = _intrinsics(f_ref * rng.uniform(*c.focal_ratio), w, h)
        target = np.array([0, 0, d / n[2]])  # the plane's point on the optical axis
        offset = rng.normal(size=3) * np.array([1, 0.6, 0.4])
        centre = offset / np.linalg.norm(offset) * rng.uniform(*c.baseline) * target[2]
        R = _rotation(rng.normal(size=3), np.deg2rad(rng.uniform(0, c.turn))) @ _look_at(centre, target)
        R = _rotation([0, 0, 1], np.deg2rad(rng.uniform(-c.roll, c.roll))) @ R
        return n, d, K_ref, K_q, R, -R @ centre

    def pair(self, index: int, rng: np.random.Generator, init_fraction: float = None) -> PairBatch:
        """A pair of photo ``index``: reference and query images, points, true and initial poses."""
        photo = self.photo(index)
        s = self.conf.max_size / max(photo.shape[:2])
        w, h = max(1, round(photo.shape[1] * s)), max(1, round(photo.shape[0] * s))
        ref = cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA)
        sx, sy = w / photo.shape[1], h / photo.shape[0]
        to_ref = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]])
        for _ in range(20):
            n, d, K_ref, K_q, R, t = self._cameras(rng, (w, h))
            uv = rng.uniform([2, 2], [w - 3, h - 3], size=(4 * self.conf.num_points, 2))
            rays = np.linalg.solve(K_ref, np.c_[uv, np.ones(len(uv))].T).T
            p3d = rays * (d / (rays @ n))[:, None]
            q = (K_q @ (p3d @ R.T + t).T).T
            inside = (q[:, 2] > 0) & np.all((q[:, :2] / q[:, 2:] >= 0) & (q[:, :2] / q[:, 2:] <= [w - 1, h - 1]), 1)
            if inside.sum() >= self.conf.min_covisible:
                break
        else:
            raise ValueError(f"No view of {self.photos[index]} keeps {self.conf.min_covisible} points in sight.")
        H = K_q @ (R + np.outer(t, n) / d) @ np.linalg.inv(K_ref)
        background = rng.uniform(0, 1, 3).astype(np.float32)
        query = cv2.warpPerspective(photo, H @ to_ref, (w, h), flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=background.tolist())
        query = (night_change if rng.uniform() < self.photo_conf.night else day_change)(query, rng)
        if rng.uniform() < self.photo_conf.occluders:
            query = occlude(query, rng, self.photo(int(rng.integers(len(self.photos)))))
        ref = day_change(ref, rng)
        keep = np.flatnonzero(inside)[:self.conf.num_points]
        num = self.conf.num_points
        points = torch.zeros(num, 3)
        points[:len(keep)] = torch.from_numpy(p3d[keep]).float()
        gt = Pose.from_Rt(torch.from_numpy(R), torch.from_numpy(t))
        fraction = init_fraction if init_fraction is not None else draw_init_fraction(self.conf, rng)
        init = initial_pose(gt, fraction)
        camera = lambda K: Camera.from_colmap("PINHOLE", w, h, [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
        image = lambda x: torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1))).float()[None]
        return PairBatch(image(ref), image(query), camera(K_ref).reshape(1), camera(K_q).reshape(1), points[None],
                         init.float().reshape(1), gt.float().reshape(1), (torch.arange(num) < len(keep))[None])

    def sample(self, rng: np.random.Generator) -> PairBatch:
        return self.pair(int(rng.integers(len(self.photos))), rng)

    def fixed(self, num: int, seed: int) -> List[PairBatch]:
        """``num`` seeded pairs (photos in a seeded order, repeated if fewer): a validation set."""
        rng = np.random.default_rng(seed)
        order = rng.permutation(len(self.photos))
        return [self.pair(int(order[k % len(order)]), rng) for k in range(num)]
