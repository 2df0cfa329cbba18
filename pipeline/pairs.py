"""Training pairs: a reference and a query view of a scene, 3D points in the reference frame,
the true relative pose and an initial pose a fraction of the way to it (official MegaDepth
sampling: a in [0.75, 1] of the relative rotation and translation)."""

from typing import List, Tuple

import numpy as np
import torch

from pixloc.geometry import Camera, Pose
from pixloc.geometry import lie
from pixloc.refiner import PairBatch

from .images import to_tensor
from .scene import CameraRecord
from .synthetic import CONDITIONS, SyntheticConfig, SyntheticScene


def initial_pose(query_from_ref: Pose, fraction: float) -> Pose:
    """The pose ``fraction`` of the way from the identity to ``query_from_ref``
    (axis-angle and translation scaled, as official PixLoc)."""
    w = lie.so3_log(query_from_ref.R) * fraction
    return Pose.from_Rt(lie.so3_exp(w), query_from_ref.t * fraction)


def synthetic_pairs(conf: SyntheticConfig, num_pairs: int, camera: CameraRecord, num_points: int = 256,
                    init_range: Tuple[float, float] = (0.75, 1.0), seed: int = 0) -> List[PairBatch]:
    """Pairs of neighbouring views of a synthetic scene; the query under a random condition.

    Points are sampled from the reference depth. Returns batches of one pair.
    """
    rng = np.random.default_rng(seed)
    scene = SyntheticScene(conf)
    refs = scene.reference_poses(max(num_pairs, 8))
    cam = camera.to_pixloc(torch.float64)
    pairs = []
    for k in range(num_pairs):
        T_ref = refs[k % len(refs)]
        # the query: a nearby viewpoint (up to ~0.5 m, ~8 degrees away)
        dT = Pose.exp(torch.from_numpy(np.concatenate([rng.normal(0, 0.25, 3), rng.normal(0, 0.07, 3)])))
        T_ref_pose = Pose.from_Rt(torch.from_numpy(T_ref[:, :3]), torch.from_numpy(T_ref[:, 3]))
        T_q_pose = dT @ T_ref_pose
        T_q = np.concatenate([T_q_pose.R.numpy(), T_q_pose.t.numpy()[:, None]], 1)
        img_ref, depth = scene.render(camera, T_ref, "day", seed=seed * 1000 + 2 * k)
        condition = CONDITIONS[rng.integers(len(CONDITIONS))]
        img_q, _ = scene.render(camera, T_q, condition, seed=seed * 1000 + 2 * k + 1)
        v, u = np.nonzero(depth > 0)
        pick = rng.choice(len(u), size=min(num_points, len(u)), replace=False)
        p2d = torch.from_numpy(np.stack([u[pick], v[pick]], 1).astype(np.float64))
        p3d_ref = cam.image2cam(p2d) * torch.from_numpy(depth[v[pick], u[pick]].astype(np.float64))[:, None]
        query_from_ref = T_q_pose @ T_ref_pose.inv()
        init = initial_pose(query_from_ref, float(rng.uniform(*init_range)))
        camera_t = Camera(cam.data.float()[None], cam.distortion)
        pairs.append(PairBatch(to_tensor(img_ref.astype(np.float32))[None], to_tensor(img_q.astype(np.float32))[None],
                               camera_t, camera_t, p3d_ref.float()[None], init.float().reshape(1),
                               query_from_ref.float().reshape(1)))
    return pairs
