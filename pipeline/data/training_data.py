"""Training pairs from any posed scene with 3D points: a reference and a query image that
see common points, the points in the reference frame, the true relative pose, and an
initial pose sampled between the reference pose and the truth (Sarlin et al. 2021, Sec. 4:
a fraction in [0.75, 1] of the way for MegaDepth; 0, the reference pose itself, for CMU).

Every source reduces to a ``Scene`` (images, points, observations): COLMAP models and
triangulations through their tracks, RGB-D and synthetic views through depth
(``rgbd_scene``). Pairs are image pairs that share at least ``min_covisible`` points;
the points of a pair are the ones observed in both images.
"""

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from pixloc.geometry import Camera, Pose, lie
from pixloc.refiner import PairBatch

from pipeline.mapping.depth import rgbd_scene
from pipeline.images import read_image, resize_max, to_tensor
from pipeline.scene import CameraRecord, ImageRecord, Scene
from pipeline.data.synthetic import SyntheticConfig, ensure_generated, read_views

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairConfig:
    """max_size: longer image side after resizing. num_points: points per pair (fewer are
    padded and masked). min_covisible: shared points for a pair. init_range: fraction of
    the way from the reference pose to the truth where the initial pose is sampled.
    far_init_prob, far_init_range: the share of pairs whose initial pose is drawn from
    ``far_init_range`` instead (farther from the truth: the basin a search must survive)."""

    max_size: int = 320
    num_points: int = 512
    min_covisible: int = 50
    init_range: Tuple[float, float] = (0.75, 1.0)
    far_init_prob: float = 0.0
    far_init_range: Tuple[float, float] = (0.25, 0.75)


def initial_pose(query_from_ref: Pose, fraction: float) -> Pose:
    """The pose ``fraction`` of the way from the identity (the reference pose) to
    ``query_from_ref``: axis-angle and translation scaled, as official PixLoc."""
    w = lie.so3_log(query_from_ref.R) * fraction
    return Pose.from_Rt(lie.so3_exp(w), query_from_ref.t * fraction)


def draw_init_fraction(conf: PairConfig, rng: np.random.Generator) -> float:
    """Where a pair's initial pose lies between the reference pose (0) and the truth (1): in
    ``init_range``, or in ``far_init_range`` for a share ``far_init_prob`` of pairs."""
    far = conf.far_init_prob > 0 and rng.uniform() < conf.far_init_prob
    return float(rng.uniform(*(conf.far_init_range if far else conf.init_range)))


def covisible_pairs(scene: Scene, min_covisible: int) -> List[Tuple[int, int]]:
    """Ordered image pairs (reference, query) sharing at least ``min_covisible`` points."""
    seen = np.zeros((len(scene.images), len(scene.points)), dtype=np.float32)
    seen[scene.obs_image, scene.obs_point] = 1
    shared = seen @ seen.T
    np.fill_diagonal(shared, 0)
    i, j = np.nonzero(shared >= min_covisible)
    return list(zip(i.tolist(), j.tolist()))


class PairDataset:
    """Pairs of one or more scenes; images are read and resized once, on first use."""

    def __init__(self, scenes: Sequence[Tuple[str, Scene]], conf: PairConfig = PairConfig(),
                 pairs: Optional[Dict[str, List[Tuple[int, int]]]] = None):
        """pairs: (reference, query) image pairs of some scenes, by name (e.g. the official
        overlap-based pairs of MegaDepth); the other scenes get their covisible pairs."""
        self.conf = conf
        self.scenes = [s for _, s in scenes]
        self.names = [n for n, _ in scenes]
        self.pairs: List[Tuple[int, int, int]] = []
        self._observed: List[List[np.ndarray]] = []
        for k, (name, scene) in enumerate(scenes):
            given = (pairs or {}).get(name)
            pairs_k = list(given) if given is not None else covisible_pairs(scene, conf.min_covisible)
            if not pairs_k:
                raise ValueError(f"Training scene {name!r} has no image pairs" + (
                    "." if given is not None else f" with >= {conf.min_covisible} common points."))
            self.pairs += [(k, i, j) for i, j in pairs_k]
            self._observed.append([np.unique(scene.obs_point[scene.obs_image == i])
                                   for i in range(len(scene.images))])
            logger.info("Training scene %s: %d images, %d points, %d pairs.", name, len(scene.images),
                        len(scene.points), len(pairs_k))
        self._cache: Dict[Tuple[int, int], Tuple[torch.Tensor, Camera]] = {}

    def __len__(self) -> int:
        return len(self.pairs)

    def image(self, k: int, i: int) -> Tuple[torch.Tensor, Camera]:
        """(3, H, W) image in [0, 1] and its Camera at the training resolution."""
        if (k, i) not in self._cache:
            record = self.scenes[k].images[i]
            image, scale = resize_max(read_image(record.path), self.conf.max_size)
            camera = record.camera.to_pixloc(torch.float64).scale(scale)
            self._cache[k, i] = (to_tensor(image), camera)
        return self._cache[k, i]

    def pair(self, index: int, rng: np.random.Generator, init_fraction: float = None) -> PairBatch:
        """Pair ``index`` as a batch of one, with points and initial pose drawn from ``rng``."""
        k, i, j = self.pairs[index]
        scene = self.scenes[k]
        common = np.intersect1d(self._observed[k][i], self._observed[k][j])
        if len(common) == 0:
            raise ValueError(f"Pair ({i}, {j}) of {self.names[k]!r} has no common points.")
        pick = rng.choice(len(common), size=min(len(common), self.conf.num_points), replace=False)
        T_ref = Pose.from_matrix(scene.images[i].cam_from_world)
        T_q = Pose.from_matrix(scene.images[j].cam_from_world)
        p3d = T_ref.transform(torch.from_numpy(scene.points[common[pick]]))
        n = self.conf.num_points
        p3d_pad = torch.zeros(n, 3, dtype=torch.float64)
        p3d_pad[:len(pick)] = p3d
        mask = torch.arange(n) < len(pick)
        query_from_ref = T_q @ T_ref.inv()
        fraction = init_fraction if init_fraction is not None else draw_init_fraction(self.conf, rng)
        init = initial_pose(query_from_ref, fraction)
        image_ref, cam_ref = self.image(k, i)
        image_q, cam_q = self.image(k, j)
        return PairBatch(image_ref[None], image_q[None], cam_ref.float().reshape(1), cam_q.float().reshape(1),
                         p3d_pad.float()[None], init.float().reshape(1), query_from_ref.float().reshape(1),
                         mask[None])

    def sample(self, rng: np.random.Generator) -> PairBatch:
        return self.pair(int(rng.integers(len(self.pairs))), rng)

    def fixed(self, num: int, seed: int) -> List[PairBatch]:
        """``num`` pairs (or all, if fewer) with seeded points and initial poses: a validation set."""
        rng = np.random.default_rng(seed)
        order = rng.permutation(len(self.pairs))[:num]
        return [self.pair(int(k), rng) for k in order]


def synthetic_scene(root, seed: int, camera: CameraRecord, num_references: int = 24,
                    queries_per_condition: int = 8, textures: Sequence[str] = ()) -> Scene:
    """A generated synthetic dataset under ``root`` (reused if generated with the same settings) as a Scene of all its
    views, references and queries in every condition, with points from their depth.
    ``textures``: photos to cover some facades with (see ``SyntheticConfig``)."""
    root = Path(root)
    ensure_generated(root, SyntheticConfig(seed=seed, textures=tuple(str(t) for t in textures)), num_references,
                     queries_per_condition, camera, query_depth=True)
    images = synthetic_images(root)
    return rgbd_scene(images, method="frames", stride=8, min_track_length=2)


def synthetic_images(root) -> List[ImageRecord]:
    """All views of a generated dataset, each with its depth, as ImageRecords."""
    images = read_views(root)
    missing = [im.name for im in images if im.depth_path is None]
    if missing:
        raise ValueError(f"Synthetic views without depth in {root}: {missing[:3]}... (generate with query_depth).")
    return images
