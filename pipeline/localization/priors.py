"""Where a query's refinement starts: one function per prior, in ``PRIORS`` (the job's ``prior``
and the command line's choices come from it), each ``(start: Start) -> Prepared``: the
query's candidates (``pipeline.localization.refine.Candidate``, several for ``hypotheses`` and
``search``), or its failure with the reason.

- ``top1``: the pose of the best reference (official PixLoc retrieval default);
- ``average``: the references' covisibility cluster averaged (``pipeline.localization.pose_averaging``);
- ``hypotheses``: each of the top ``num_hypotheses`` reference poses, the most confident
  refinement wins;
- ``search``: the top references' poses, the average pose and perturbations of each, screened
  at the coarsest level (``pipeline.localization.search``);
- ``poses``: refinement mode from another pipeline's poses file (``prior_poses``);
- ``hloc``: refinement mode from hloc's logs (its PnP pose, the references with most inliers,
  optionally only the inlier points), as the paper's;
- ``sift``: SIFT matches to the references, PnP (``pipeline.localization.sift``), refined on the
  two finest levels; where PnP finds too few inliers, the ``search`` prior.

A new prior is a function here and its line in ``PRIORS``.
"""

import functools
import logging
from dataclasses import dataclass, replace
from typing import Any, Callable, Dict, List, Optional, Tuple, Union

import numpy as np

from pipeline.localization.refine import Candidate, QueryResult
from pipeline.store.reader import MapReader
from pipeline.localization.pose_averaging import covisibility_clusters, pose_approximation
from pipeline.queries import QueryRecord
from pipeline.mapping.readers.hloc import PnPLog, read_hloc_logs
from pipeline.localization.retrieval import Retrieved
from pipeline.localization.sift import FALLBACK, sift_pnp
from pipeline.localization.search import Hypotheses, hypotheses, median_depth
from pipeline.textfiles import NameIndex, PoseTable, find_by_name, read_poses

logger = logging.getLogger(__name__)

Prepared = Union[QueryResult, List[Candidate]]  # a Hypotheses is a list of candidates too


@dataclass
class Start:
    """What a prior works from: the job (``pipeline.localization.shard.LocalizationJob``: the prior's
    settings), the map, the query with its decoded image and its cache, and its references
    (``references()``: retrieved when first asked, so that ``hloc`` runs no retrieval)."""

    job: Any
    reader: MapReader
    query: QueryRecord
    rgb: np.ndarray
    cache: Dict
    references: Callable[[], Retrieved]

    def candidate(self, dbs: List[int], prior: np.ndarray, origin: str,
                  selected: Optional[np.ndarray] = None, levels: Optional[Tuple[int, ...]] = None) -> Candidate:
        return Candidate(self.query, list(dbs), np.asarray(prior, np.float64), self.rgb, self.cache, selected, origin,
                         levels=levels)


def failure(query: QueryRecord, reason: str, prior=None, refs=None) -> QueryResult:
    """A query that cannot be refined, with the reason (and the prior it has, if any)."""
    return QueryResult(query.name, False, prior, None, list(refs or []), reason=reason, notes=list(query.notes))


NO_MATCH = "no retrieval match among the map's usable reference images"


def top1(s: Start) -> Prepared:
    r = s.references()
    if not r.dbs:
        return failure(s.query, NO_MATCH)
    return [s.candidate(r.dbs[:s.job.localizer.num_dbs], s.reader.cam_from_world[r.dbs[0]], "top-1 reference")]


def average_pose(s: Start, r: Retrieved) -> Tuple[List[int], np.ndarray]:
    """The covisibility cluster of the top references and its similarity-weighted average pose."""
    similarity = r.similarity if r.similarity is not None else np.ones(len(r.dbs))
    sim = dict(zip(r.dbs, similarity))
    cluster = covisibility_clusters(r.dbs[:s.job.localizer.num_dbs], s.reader.image_points)[0]
    return cluster, pose_approximation([s.reader.cam_from_world[i] for i in cluster], [sim[i] for i in cluster])


def average(s: Start) -> Prepared:
    r = s.references()
    if not r.dbs:
        return failure(s.query, NO_MATCH)
    cluster, prior = average_pose(s, r)
    return [s.candidate(cluster, prior, "average pose")]


def reference_hypotheses(s: Start) -> Prepared:
    r = s.references()
    if not r.dbs:
        return failure(s.query, NO_MATCH)
    dbs = r.dbs[:s.job.localizer.num_dbs]
    return [s.candidate(dbs, s.reader.cam_from_world[i], f"reference {n + 1}")
            for n, i in enumerate(r.dbs[:s.job.num_hypotheses])]


def search(s: Start) -> Prepared:
    r = s.references()
    if not r.dbs:
        return failure(s.query, NO_MATCH)
    conf = s.job.search
    prior = average_pose(s, r)[1] if conf.average else None
    starts = hypotheses(s.reader, r.dbs, conf, prior)
    # always refined: the top-1 pose (first) and the average pose (first of the last block)
    always = [0] + ([len(starts) - conf.size()] if conf.average else [])
    dbs = r.dbs[:s.job.localizer.num_dbs]
    return Hypotheses([s.candidate(dbs, T, label) for T, label in starts], always=always,
                      depth=median_depth(s.reader, r.dbs[0]))


@functools.lru_cache(maxsize=2)
def poses_file(path: str) -> PoseTable:
    """A poses file (priors), read once per process (``pipeline.textfiles.read_poses``)."""
    return read_poses(path)


def other_pipeline(s: Start) -> Prepared:
    r = s.references()
    if not r.dbs:
        return failure(s.query, NO_MATCH)
    dbs = r.dbs[:s.job.localizer.num_dbs]
    prior = poses_file(s.job.prior_poses).find(s.query.name)
    if prior is None:
        return failure(s.query, f"no prior pose for this query in {s.job.prior_poses}", refs=dbs)
    return [s.candidate(dbs, prior, f"pose in {s.job.prior_poses}")]


@functools.lru_cache(maxsize=2)
def hloc_logs(path: str) -> Tuple[Dict[str, PnPLog], NameIndex]:
    """The logs of an hloc ``_logs.pkl`` and their name index, built once per process."""
    logs = read_hloc_logs(path)
    return logs, NameIndex(logs, path)


def hloc(s: Start) -> Prepared:
    """Refinement mode from hloc's logs (official PoseRefiner): start from the PnP pose, use the
    references that gave the most inliers, optionally only the inlier points."""
    job, reader, query = s.job, s.reader, s.query
    logs, index = hloc_logs(job.hloc_logs)
    log = find_by_name(logs, query.name, index)
    if log is None:
        return failure(query, f"no hloc log for this query in {job.hloc_logs}")
    if not log.success:
        return failure(query, "hloc PnP failed: no initial pose")
    prior = log.cam_from_world
    if log.num_inliers < job.min_inliers:
        return failure(query, f"hloc PnP has {log.num_inliers} inliers (< {job.min_inliers})", prior)
    images, points = reader.source_ids
    inliers = log.inliers_per_db()
    ranked = [log.db_ids[i] for i in np.argsort(-inliers, kind="stable") if inliers[i] > job.min_matches_db]
    ranked = [i for i in ranked if i in images and reader.usable(images[i])][:job.localizer.num_dbs]
    if not ranked:
        unknown = [i for i in log.db_ids if i not in images]
        reason = (f"none of the log's references (COLMAP image ids {unknown[:5]}) is in the map: build the "
                  "store from the SfM model hloc localized against" if len(unknown) == len(log.db_ids) else
                  f"no usable reference with more than {job.min_matches_db} PnP inliers")
        return failure(query, reason, prior)
    selected = None
    if job.point_selection != "all":
        pairs = log.inlier_observations(ranked, inliers_only=job.point_selection == "inliers")
        known = [(points[p], images[i]) for p, i in pairs if p in points]
        if len(known) < len(pairs):
            logger.warning("%s: %d of %d hloc matches name points that are not in the map.", query.name,
                           len(pairs) - len(known), len(pairs))
        selected = np.array(known, dtype=np.int64).reshape(-1, 2)
    return [s.candidate([images[i] for i in ranked], prior, "hloc PnP pose", selected)]


def sift(s: Start) -> Prepared:
    """The SIFT + PnP pose, refined; the search prior where PnP fails. Each query's notes say which."""
    r = s.references()
    if not r.dbs:
        return failure(s.query, NO_MATCH)
    dbs = r.dbs[:s.job.localizer.num_dbs]
    found = sift_pnp(s.reader, dbs, s.rgb, s.query.camera, s.job.sift)
    if found.pose is None:
        note = f"{found.describe()}: fewer than {s.job.sift.min_inliers} inliers, {FALLBACK}"
        return search(replace(s, query=replace(s.query, notes=s.query.notes + (note,))))
    noted = replace(s, query=replace(s.query, notes=s.query.notes + (found.describe(),)))
    return [noted.candidate(dbs, found.pose, "SIFT PnP pose", levels=s.job.sift.levels)]


PRIORS: Dict[str, Callable[[Start], Prepared]] = {
    "top1": top1, "average": average, "hypotheses": reference_hypotheses, "search": search,
    "poses": other_pipeline, "hloc": hloc, "sift": sift}
