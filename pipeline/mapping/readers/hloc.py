"""hloc localization logs (``<results>_logs.pkl`` of hloc's ``localize_sfm``): the PnP
pose of each query and its 2D-3D matches, for PixLoc's refinement mode.

Per query, ``logs["loc"][name]`` holds ``db`` (the COLMAP image ids of the retrieved
references), ``PnP_ret`` (``success``, the pose as ``qvec``/``tvec`` or, in newer hloc, a
``cam_from_world`` pycolmap Rigid3d, ``num_inliers``, ``inliers`` one flag per match) and
``keypoint_index_to_db``: ``(keypoint indices, [(point3D_id, [indices into db]), ...])``, one
entry per match. Ids are those of the SfM model hloc localized against, so the map store
must be built from that model (it records them as ``source_id``).
"""

from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np

from pipeline.scene import SceneError, qvec_to_rotmat
from pipeline.mapping.readers.safe_pickle import load_data_pickle

# pycolmap data classes that newer hloc versions pickle in PnP_ret
_PYCOLMAP = frozenset((m, n) for m in ("pycolmap", "pycolmap._core", "pycolmap.pycolmap")
                      for n in ("Rigid3d", "Rotation3d"))


@dataclass
class PnPLog:
    """hloc's localization of one query.

    db_ids: COLMAP image ids of the retrieved references. match_points: (M,) COLMAP
    point3D ids of the 2D-3D matches; match_dbs: per match, the indices into ``db_ids`` of
    the references whose keypoints gave it; inliers: (M,) bool, the PnP inliers.
    """

    success: bool
    cam_from_world: Optional[np.ndarray]
    num_inliers: int
    db_ids: List[int]
    match_points: np.ndarray
    match_dbs: List[List[int]]
    inliers: np.ndarray

    def inliers_per_db(self) -> np.ndarray:
        """(len(db_ids),) number of PnP inliers each reference contributed (official get_db_inliers)."""
        count = np.zeros(len(self.db_ids), dtype=np.int64)
        for dbs, inlier in zip(self.match_dbs, self.inliers):
            if inlier:
                np.add.at(count, list(dbs), 1)  # a reference listed twice counts twice, as official
        return count

    def inlier_observations(self, db_ids: List[int], inliers_only: bool = True) -> np.ndarray:
        """(K, 2) unique (point3D_id, image_id) pairs: the matches (inliers only by default)
        and the references among ``db_ids`` that gave them (official get_p3did_to_dbids)."""
        keep = set(db_ids)
        pairs = {(int(p), int(self.db_ids[d])) for p, dbs, inlier in zip(self.match_points, self.match_dbs,
                                                                           self.inliers)
                 if inlier or not inliers_only for d in dbs if int(self.db_ids[d]) in keep}
        return np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2)


def _pose(ret: Dict) -> Optional[np.ndarray]:
    if "qvec" in ret and "tvec" in ret:
        return np.concatenate([qvec_to_rotmat(ret["qvec"]), np.asarray(ret["tvec"], float).reshape(3, 1)], 1)
    if "cam_from_world" in ret:
        return np.asarray(ret["cam_from_world"].matrix(), dtype=np.float64)
    return None


def parse_loc(name: str, loc: Dict) -> PnPLog:
    """One query's log. With covisibility clustering (Aachen practice), hloc keeps one log per
    cluster under ``log_clusters`` and the index of the cluster with most inliers under
    ``best_cluster`` (None when PnP failed in every cluster); that cluster's log is the pose."""
    if "log_clusters" in loc:
        best = loc.get("best_cluster")
        clusters = loc.get("log_clusters") or []
        if best is None or not 0 <= int(best) < len(clusters):
            return PnPLog(False, None, 0, [int(i) for i in loc.get("db", [])], np.zeros(0, np.int64), [],
                          np.zeros(0, bool))
        loc = clusters[int(best)]
    ret = loc.get("PnP_ret") or {}
    success = bool(ret.get("success", False))
    pose = _pose(ret) if success else None
    if success and pose is None:
        raise SceneError(f"hloc log of {name}: PnP_ret has no pose (qvec/tvec or cam_from_world).")
    matches = loc.get("keypoint_index_to_db", ((), ()))[1]
    points = np.array([int(p) for p, _ in matches], dtype=np.int64)
    dbs = [[int(d) for d in ds] for _, ds in matches]
    inliers = np.asarray(ret.get("inliers", np.zeros(len(points), bool)), dtype=bool).reshape(-1)
    if success and len(inliers) != len(points):
        raise SceneError(f"hloc log of {name}: {len(inliers)} inlier flags for {len(points)} matches.")
    db_ids = [int(i) for i in loc.get("db", [])]
    if any(not 0 <= i < 2**32 for i in db_ids):
        raise SceneError(f"hloc log of {name}: a reference id (db) is not a COLMAP image id.")
    if any(not 0 <= d < len(db_ids) for ds in dbs for d in ds):
        raise SceneError(f"hloc log of {name}: a match names a reference beyond its {len(db_ids)} (db).")
    return PnPLog(success, pose, int(ret.get("num_inliers", int(inliers.sum()))), db_ids, points, dbs, inliers)


def read_hloc_logs(path) -> Dict[str, PnPLog]:
    """``query name -> PnPLog`` from an hloc ``_logs.pkl`` file."""
    logs = load_data_pickle(path, "hloc localization log", _PYCOLMAP)
    if not isinstance(logs, dict) or not isinstance(logs.get("loc"), dict):
        raise SceneError(f"{path} is not an hloc localization log: it has no 'loc' entry.")
    parsed = {}
    for name, loc in logs["loc"].items():
        try:
            parsed[str(name)] = log = parse_loc(str(name), loc)
        except (AttributeError, TypeError, ValueError, KeyError, IndexError, OverflowError) as e:
            if isinstance(e, SceneError):
                raise SceneError(f"{path}: {e}") from None
            raise SceneError(f"{path}: the log of {name} is not what hloc writes ({type(e).__name__}: {e}).") from None
        if log.cam_from_world is not None and not np.isfinite(log.cam_from_world).all():
            raise SceneError(f"{path}: the PnP pose of {name} is not finite.")
    return parsed
