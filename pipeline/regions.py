"""Queries ordered by the map region their references lie in, so that a shard reads a bounded
part of the map store.

After retrieval, each query is placed at the camera centre of its top-1 reference. The centres
are projected on the two main axes of the reference cameras (PCA: the ground plane of a city)
and sorted along a Z-order (Morton) curve, which keeps nearby points together: consecutive
queries, hence the queries of one shard, share references and the worker's block cache hits.
"""

from typing import Dict, List, Optional, Sequence

import numpy as np


def camera_centres(cam_from_world: np.ndarray) -> np.ndarray:
    """(N, 3, 4) cam_from_world -> (N, 3) centres -R^T t."""
    T = np.asarray(cam_from_world, np.float64)
    return -np.einsum("nji,nj->ni", T[:, :, :3], T[:, :, 3])


def morton(xy: np.ndarray, bits: int = 16) -> np.ndarray:
    """Z-order codes of (N, 2) points (normalised to their bounding box, ``bits`` per axis)."""
    lo, hi = xy.min(0), xy.max(0)
    q = np.floor((xy - lo) / np.maximum(hi - lo, 1e-12) * (2 ** bits - 1)).astype(np.uint64)
    code = np.zeros(len(xy), np.uint64)
    for b in range(bits):
        for axis in range(2):
            code |= ((q[:, axis] >> np.uint64(b)) & np.uint64(1)) << np.uint64(2 * b + axis)
    return code


def region_order(names: Sequence[str], top1: Dict[str, Optional[str]], reference_names: Sequence[str],
                 reference_centres: np.ndarray) -> List[int]:
    """Indices of ``names`` in region order: by the Z-order code of their top-1 reference's centre
    (ties and equal references in list order); queries without a reference last, in list order."""
    index = {n: i for i, n in enumerate(reference_names)}
    centres = np.asarray(reference_centres, np.float64)
    mean = centres.mean(0)
    _, _, vt = np.linalg.svd(centres - mean, full_matrices=False)
    plane = (centres - mean) @ vt[:2].T if len(centres) > 1 else np.zeros((len(centres), 2))
    codes = morton(plane) if len(centres) else np.zeros(0, np.uint64)
    placed = [(int(codes[index[top1[n]]]), index[top1[n]], k) for k, n in enumerate(names)
              if top1.get(n) in index]
    rest = [k for k, n in enumerate(names) if top1.get(n) not in index]
    return [k for _, _, k in sorted(placed)] + rest
