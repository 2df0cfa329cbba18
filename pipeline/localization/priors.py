"""Where a query's refinement starts: the registry ``PRIORS`` (the job's ``prior`` and the command
line's choices come from it). An entry is its settings dataclass: ``start(start, references) ->
Prepared`` (``prepare(start)`` for a prior that retrieves nothing) gives the query's candidates
(``pipeline.localization.refine.Candidate``, several for ``hypotheses`` and ``search``), or its
failure with the reason.

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

An entry's class attributes: ``help`` (the command line's), ``flags`` (its own options, relative
to its fields), ``retrieves`` (it asks for the query's references: a retrieval method runs),
``rivals`` (its start is a map image's pose: other references' poses check it,
``search.rival_starts``), ``given_poses`` (it refines another pipeline's poses: a preset's
``from_poses`` settings apply), ``inputs`` (its fields that name input files). A new prior is one
class here.
"""

import functools
import logging
from dataclasses import dataclass, replace
from typing import Callable, ClassVar, Dict, List, Optional, Tuple, Union

import numpy as np

from pipeline.localization.candidates import Candidate, Keypoints, QueryCache, QueryResult
from pipeline.store.reader import MapReader
from pipeline.localization.pose_averaging import covisibility_clusters, pose_approximation
from pipeline.queries import QueryRecord
from pipeline.mapping.readers.hloc import PnPLog, read_hloc_logs
from pipeline.localization.retrieval import Retrieved
from pipeline.localization.sift import FALLBACK, SiftConfig, sift_pnp
from pipeline.localization.search import Hypotheses, SearchConfig, hypotheses, median_depth
from pipeline.registry import Registry, check_inputs
from pipeline.settings import Flag
from pipeline.textfiles import NameIndex, find_by_name, poses_file

logger = logging.getLogger(__name__)

Prepared = Union[QueryResult, List[Candidate]]  # a Hypotheses is a list of candidates too


@dataclass
class Start:
    """What a prior works from: the map, the query with its decoded image and its cache, the
    references a query is refined against (``num_dbs``), and its retrieved references
    (``references()``: retrieved when first asked, so that ``hloc`` runs no retrieval)."""

    reader: MapReader
    query: QueryRecord
    rgb: np.ndarray
    cache: QueryCache
    references: Callable[[], Retrieved]
    num_dbs: int

    def candidate(self, dbs: List[int], prior: np.ndarray, origin: str,
                  selected: Optional[np.ndarray] = None, levels: Optional[Tuple[int, ...]] = None,
                  keypoints: Optional[Keypoints] = None) -> Candidate:
        return Candidate(self.query, list(dbs), np.asarray(prior, np.float64), self.rgb, self.cache, selected, origin,
                         levels=levels, keypoints=keypoints)


def failure(query: QueryRecord, reason: str, prior=None, refs=None) -> QueryResult:
    """A query that cannot be refined, with the reason (and the prior it has, if any)."""
    return QueryResult(query.name, False, prior, None, list(refs or []), reason=reason, notes=list(query.notes))


NO_MATCH = "no retrieval match among the map's usable reference images"


@dataclass(frozen=True)
class PriorSettings:
    """The settings of one prior (an entry of ``PRIORS``); see the module docstring."""

    name: ClassVar[str]
    help: ClassVar[str] = ""
    flags: ClassVar[Dict[str, Flag]] = {}
    retrieves: ClassVar[bool] = True
    rivals: ClassVar[bool] = False
    given_poses: ClassVar[bool] = False
    inputs: ClassVar[Tuple[str, ...]] = ()

    def prepare(self, s: Start) -> Prepared:
        """The query's starts from its references (``start``), or its failure where it has none."""
        r = s.references()
        if not r.dbs:
            return failure(s.query, NO_MATCH)
        return self.start(s, r)

    def start(self, s: Start, r: Retrieved) -> Prepared:
        raise NotImplementedError

    def validate(self) -> None:
        """Refuse settings that cannot run, before any query does (ValueError); input files are
        read in full now: a bad line is one clear error (file:line), not the same failure in every
        query."""
        check_inputs(self, f"--prior {self.name}")


PRIORS = Registry("prior")


@PRIORS.register("top1")
@dataclass(frozen=True)
class Top1(PriorSettings):
    help: ClassVar[str] = "the pose of the best reference"
    rivals: ClassVar[bool] = True

    def start(self, s: Start, r: Retrieved) -> Prepared:
        return [s.candidate(r.dbs[:s.num_dbs], s.reader.cam_from_world[r.dbs[0]], "top-1 reference")]


def average_pose(s: Start, r: Retrieved) -> Tuple[List[int], np.ndarray]:
    """The covisibility cluster of the top references and its similarity-weighted average pose."""
    similarity = r.similarity if r.similarity is not None else np.ones(len(r.dbs))
    sim = dict(zip(r.dbs, similarity))
    cluster = covisibility_clusters(r.dbs[:s.num_dbs], s.reader.image_points)[0]
    return cluster, pose_approximation([s.reader.cam_from_world[i] for i in cluster], [sim[i] for i in cluster])


@PRIORS.register("average")
@dataclass(frozen=True)
class Average(PriorSettings):
    help: ClassVar[str] = "the references' covisibility cluster, its poses averaged"
    rivals: ClassVar[bool] = True

    def start(self, s: Start, r: Retrieved) -> Prepared:
        cluster, prior = average_pose(s, r)
        return [s.candidate(cluster, prior, "average pose")]


@PRIORS.register("hypotheses")
@dataclass(frozen=True)
class ReferenceHypotheses(PriorSettings):
    """num_hypotheses: the top references whose poses are each refined (the most confident wins)."""

    num_hypotheses: int = 3
    help: ClassVar[str] = "each top reference's pose refined, the most confident wins"
    rivals: ClassVar[bool] = True

    def validate(self) -> None:
        if self.num_hypotheses < 1:
            raise ValueError("num_hypotheses must be at least 1.")

    def start(self, s: Start, r: Retrieved) -> Prepared:
        dbs = r.dbs[:s.num_dbs]
        return [s.candidate(dbs, s.reader.cam_from_world[i], f"reference {n + 1}")
                for n, i in enumerate(r.dbs[:self.num_hypotheses])]


def search_starts(s: Start, r: Retrieved, conf: SearchConfig) -> Prepared:
    """The search's starts (``pipeline.localization.search``) around the query's references ``r``."""
    prior = average_pose(s, r)[1] if conf.average else None
    starts = hypotheses(s.reader, r.dbs, conf, prior)
    # always refined: the top-1 pose (first) and the average pose (first of the last block)
    always = [0] + ([len(starts) - conf.size()] if conf.average else [])
    dbs = r.dbs[:s.num_dbs]
    return Hypotheses([s.candidate(dbs, T, label) for T, label in starts], always=always,
                      depth=median_depth(s.reader, r.dbs[0]))


@PRIORS.register("search")
@dataclass(frozen=True)
class Search(PriorSettings):
    search: SearchConfig = SearchConfig()
    help: ClassVar[str] = "many starts around the top references, screened at the coarsest level"

    def validate(self) -> None:
        self.search.validate()

    def start(self, s: Start, r: Retrieved) -> Prepared:
        return search_starts(s, r, self.search)


@PRIORS.register("poses")
@dataclass(frozen=True)
class OtherPipeline(PriorSettings):
    """prior_poses: the poses file of another pipeline (visuallocalization.net format)."""

    prior_poses: Optional[str] = None
    help: ClassVar[str] = "refinement mode: another pipeline's poses (--prior-poses)"
    flags: ClassVar[Dict[str, Flag]] = {
        "--prior-poses": Flag("prior_poses", "refinement mode: poses file of another pipeline", file=True)}
    given_poses: ClassVar[bool] = True
    inputs: ClassVar[Tuple[str, ...]] = ("prior_poses",)

    def validate(self) -> None:
        super().validate()
        poses_file(self.prior_poses)

    def start(self, s: Start, r: Retrieved) -> Prepared:
        dbs = r.dbs[:s.num_dbs]
        prior = poses_file(self.prior_poses).find(s.query.name)
        if prior is None:
            return failure(s.query, f"no prior pose for this query in {self.prior_poses}",
                           refs=[s.reader.names[i] for i in dbs])
        return [s.candidate(dbs, prior, f"pose in {self.prior_poses}")]


@functools.lru_cache(maxsize=2)
def hloc_logs(path: str) -> Tuple[Dict[str, PnPLog], NameIndex]:
    """The logs of an hloc ``_logs.pkl`` and their name index, built once per process."""
    logs = read_hloc_logs(path)
    return logs, NameIndex(logs, path)


POINT_SELECTIONS = ("all", "inliers", "matched")


@PRIORS.register("hloc")
@dataclass(frozen=True)
class Hloc(PriorSettings):
    """Refinement mode from hloc's logs (official PoseRefiner): start from the PnP pose, use the
    references that gave the most inliers (more than ``min_matches_db``), optionally only the
    inlier points. point_selection: ``all`` points of the kept references, ``inliers`` (the PnP
    inliers only, observed by the references that matched them) or ``matched`` (all 2D-3D
    matches); queries with fewer than ``min_inliers`` inliers fail. The store must be built from
    the SfM model hloc used."""

    hloc_logs: Optional[str] = None
    point_selection: str = "all"
    min_matches_db: int = 10
    min_inliers: int = 10
    help: ClassVar[str] = "refinement mode from an hloc _logs.pkl (its PnP poses and inliers)"
    flags: ClassVar[Dict[str, Flag]] = {
        "--hloc-logs": Flag("hloc_logs", "refinement mode: hloc localization logs (_logs.pkl); the store must be "
                            "built from the SfM model hloc localized against", file=True),
        "--point-selection": Flag("point_selection", "with --prior hloc: all points of the references, or hloc's "
                                  "PnP inliers (paper) or matches", POINT_SELECTIONS)}
    retrieves: ClassVar[bool] = False
    given_poses: ClassVar[bool] = True
    inputs: ClassVar[Tuple[str, ...]] = ("hloc_logs",)

    def validate(self) -> None:
        if self.point_selection not in POINT_SELECTIONS:
            raise ValueError(f"Unknown point selection {self.point_selection!r}: use one of "
                             f"{', '.join(POINT_SELECTIONS)}.")
        super().validate()

    def prepare(self, s: Start) -> Prepared:
        reader, query = s.reader, s.query
        logs, index = hloc_logs(self.hloc_logs)
        log = find_by_name(logs, query.name, index)
        if log is None:
            return failure(query, f"no hloc log for this query in {self.hloc_logs}")
        if not log.success:
            return failure(query, "hloc PnP failed: no initial pose")
        prior = log.cam_from_world
        if log.num_inliers < self.min_inliers:
            return failure(query, f"hloc PnP has {log.num_inliers} inliers (< {self.min_inliers})", prior)
        images, points = reader.source_ids
        inliers = log.inliers_per_db()
        ranked = [log.db_ids[i] for i in np.argsort(-inliers, kind="stable") if inliers[i] > self.min_matches_db]
        ranked = [i for i in ranked if i in images and reader.usable(images[i])][:s.num_dbs]
        if not ranked:
            unknown = [i for i in log.db_ids if i not in images]
            reason = (f"none of the log's references (COLMAP image ids {unknown[:5]}) is in the map: build the "
                      "store from the SfM model hloc localized against" if len(unknown) == len(log.db_ids) else
                      f"no usable reference with more than {self.min_matches_db} PnP inliers")
            return failure(query, reason, prior)
        selected = None
        if self.point_selection != "all":
            pairs = log.inlier_observations(ranked, inliers_only=self.point_selection == "inliers")
            known = [(points[p], images[i]) for p, i in pairs if p in points]
            if len(known) < len(pairs):
                logger.warning("%s: %d of %d hloc matches name points that are not in the map.", query.name,
                               len(pairs) - len(known), len(pairs))
            selected = np.array(known, dtype=np.int64).reshape(-1, 2)
        return [s.candidate([images[i] for i in ranked], prior, "hloc PnP pose", selected)]


@PRIORS.register("sift")
@dataclass(frozen=True)
class Sift(PriorSettings):
    """The SIFT + PnP pose, refined; the search prior (``search``) where PnP fails. Each query's
    notes say which. keypoint_weight: the weight of the PnP inliers' reprojection error in the
    refinement's cost, beside the featuremetric cost, each normalised by its residual scale
    (``pixloc.optim.keypoints``; 0: the features alone, as the official refinement of PnP poses)."""

    sift: SiftConfig = SiftConfig()
    search: SearchConfig = SearchConfig()
    keypoint_weight: float = 1.0
    help: ClassVar[str] = "SIFT matches to the references and PnP (the search where PnP fails)"
    flags: ClassVar[Dict[str, Flag]] = {
        "--sift-min-inliers": Flag("sift.min_inliers", "with --prior sift: PnP inliers a pose needs"),
        "--sift-max-size": Flag("sift.max_size", "with --prior sift: longer image side of SIFT extraction"),
        "--sift-levels": Flag("sift.levels", "with --prior sift: the levels a PnP pose is refined on (the two "
                              "finest, as the official refinement of PnP poses; 0 1 2: every level)"),
        "--sift-keypoint-weight": Flag("keypoint_weight", "with --prior sift: the weight of the PnP inliers' "
                                       "reprojection error in the refinement, beside the features (0: features "
                                       "alone)")}

    def validate(self) -> None:
        self.search.validate()
        self.sift.validate()
        if not self.keypoint_weight >= 0:
            raise ValueError(f"keypoint_weight must not be negative, not {self.keypoint_weight}.")

    def start(self, s: Start, r: Retrieved) -> Prepared:
        dbs = r.dbs[:s.num_dbs]
        found = sift_pnp(s.reader, dbs, s.rgb, s.query.camera, self.sift)
        if found.pose is None:
            note = f"{found.describe()}: fewer than {self.sift.min_inliers} inliers, {FALLBACK}"
            return search_starts(replace(s, query=replace(s.query, notes=s.query.notes + (note,))), r, self.search)
        noted = replace(s, query=replace(s.query, notes=s.query.notes + (found.describe(),)))
        keypoints = replace(found.keypoints, weight=self.keypoint_weight)
        return [noted.candidate(dbs, found.pose, "SIFT PnP pose", levels=self.sift.levels, keypoints=keypoints)]


@PRIORS.register("pnp")
@dataclass(frozen=True)
class PnP(PriorSettings):
    """The SIFT + PnP pose itself, not refined: the classical pipeline that ``sift`` refines, as its
    peer. A query whose PnP finds fewer than ``sift.min_inliers`` inliers fails, with no fallback."""

    sift: SiftConfig = SiftConfig()
    help: ClassVar[str] = "SIFT matches to the references and PnP, the pose reported as PnP gives it (not refined)"
    flags: ClassVar[Dict[str, Flag]] = {
        "--pnp-min-inliers": Flag("sift.min_inliers", "with --prior pnp: PnP inliers a pose needs")}

    def validate(self) -> None:
        self.sift.validate()

    def start(self, s: Start, r: Retrieved) -> Prepared:
        refs = [s.reader.names[i] for i in r.dbs[:s.num_dbs]]
        found = sift_pnp(s.reader, r.dbs[:s.num_dbs], s.rgb, s.query.camera, self.sift)
        notes = list(s.query.notes) + [found.describe()]
        if found.pose is None:
            return QueryResult(s.query.name, False, None, None, refs, notes=notes,
                               reason=f"PnP found {found.inliers} inliers (< {self.sift.min_inliers})")
        return QueryResult(s.query.name, True, found.pose, found.pose, refs, notes=notes + ["not refined (prior pnp)"],
                           evidence={"pnp_inliers": float(found.inliers),
                                     "pnp_correspondences": float(found.correspondences)})
