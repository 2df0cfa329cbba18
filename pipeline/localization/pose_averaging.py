"""Reference poses averaged into one prior (the ``average`` prior of ``pipeline.localization.priors``), as
the paper's appendix and official ``do_pose_approximation``: keep the largest covisibility
cluster of the top-k references, and average their poses with weights (cosine similarity)^8:
centres linearly, rotations by quaternion averaging (Markley et al. 2007, "Averaging
Quaternions").
"""

from typing import Callable, List, Sequence

import numpy as np

from pipeline.scene import qvec_to_rotmat, rotmat_to_qvec


def covisibility_clusters(dbs: Sequence[int], image_points: Callable[[int], np.ndarray]) -> List[List[int]]:
    """Connected components of ``dbs`` where two images are linked if they see a common point
    (``image_points(i)``: the points of image i); largest first, ties by the rank of their best
    image (official ``do_covisibility_clustering``)."""
    points = {i: set(image_points(i).tolist()) for i in dbs}
    clusters, visited = [], set()
    for start in dbs:
        if start in visited:
            continue
        cluster, queue = [], [start]
        while queue:
            i = queue.pop()
            if i in visited:
                continue
            visited.add(i)
            cluster.append(i)
            queue += [j for j in dbs if j not in visited and points[i] & points[j]]
        clusters.append(cluster)
    return sorted(clusters, key=len, reverse=True)


def average_poses(poses: Sequence[np.ndarray], weights: Sequence[float]) -> np.ndarray:
    """Weighted average of cam_from_world (3, 4) poses: camera centres linearly, rotations by
    the principal eigenvector of sum w q q^T (Markley)."""
    w = np.asarray(weights, np.float64)
    w = w / w.sum()
    Rs = [np.asarray(T)[:, :3] for T in poses]
    centres = np.stack([-R.T @ np.asarray(T)[:, 3] for R, T in zip(Rs, poses)])
    qs = np.stack([rotmat_to_qvec(R) for R in Rs])
    M = (w[:, None, None] * qs[:, :, None] * qs[:, None, :]).sum(0)
    q = np.linalg.eigh(M)[1][:, -1]
    R = qvec_to_rotmat(q)
    c = (w[:, None] * centres).sum(0)
    return np.concatenate([R, (-R @ c)[:, None]], 1)


def pose_approximation(poses: Sequence[np.ndarray], similarities: Sequence[float], alpha: float = 8.0
                       ) -> np.ndarray:
    """Official ``pose_approximation``: weights = similarity^alpha."""
    s = np.clip(np.asarray(similarities, np.float64), 0, None)
    weights = s ** alpha if (s > 0).any() else np.ones_like(s)
    return average_poses(poses, weights)
