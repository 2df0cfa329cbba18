"""Localization of one query against a map store: PixLoc's coarse-to-fine refinement.

As the official ``RetrievalRefiner`` / ``BaseRefiner``: the 3D points seen by
the selected reference images (track length >= ``min_track_length``), their
stored reference features (observations invalid at any level dropped), either
averaged per point weighted by confidence or each kept as its own residual,
then per image scale the query's dense features and LM from the coarsest to
the finest level. A failure at any level keeps the prior, marked failed.
"""

import copy
import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch.nn.functional import normalize

from pixloc.geometry import Camera, Pose, relative_motion
from pixloc.optim import (FeaturemetricProblem, LevenbergMarquardt, alignment_contrast, alignment_evidence,
                          alignment_uncertainty)
from pixloc.optim.cost import new_query_maps
from pixloc.optim.keypoints import KeypointTerm
from pixloc.nets.unet import NETWORK_PRECISIONS, UNet, predict_in_precision

from pipeline.images import ImageReadError, read_image_for, resize_max, to_tensor
from pipeline import kernels
from pipeline.localization.finest import FinestFill, level_like, level_shape, write_level
from pipeline.store.reader import MapReader, Observations, StoreReadError
from pipeline.queries import QueryRecord
from pipeline.localization.candidates import BodyRef, Candidate, Keypoints, QueryCache, QueryResult  # noqa: F401
from pipeline.localization.bodies import group_bodies, split_bodies
from pipeline.localization.verify import VerificationConfig, keep_start, verify

logger = logging.getLogger(__name__)
# pixels at the finest level of the contrast that verification reads (pixloc.optim.evidence); the
# measurement of docs/verification.md also recorded 1 and 10 px and a depth contrast: none did better
CONTRAST_SHIFTS = (3.0,)
MIN_SUBSET = 1024  # the fewest points a level is subsampled to (points_per_cell)
JOINED = "joined: "  # the reason of a rival start stopped where it reached its query's own start


@dataclass(frozen=True)
class LocalizerConfig:
    """num_dbs: reference images used. average_observations: one residual per point
    (confidence-weighted mean over references) instead of one per observation.
    num_iters: LM iterations per level. min_track_length, min_points: official filters
    (points seen by fewer images of the whole map than ``min_track_length`` are left out;
    fewer than ``min_points`` points fails the query). verification: when a refined pose is
    accepted (``pipeline.localization.verify``). points_per_cell: at a level whose query feature map has
    fewer cells than points / ``points_per_cell``, LM runs on a seeded subset of
    max(``MIN_SUBSET``, points_per_cell x cells) of them (0: every point, as official PixLoc).
    Dense (RGB-D) maps put tens of thousands of points into the few hundred cells of the
    coarse levels, where they are redundant and cost nearly all the time. network_precision:
    the query's network pass in float32; bfloat16 (autocast; the LM stays float32): a query's CPU
    time 0.8x at Cambridge settings on a CPU with AVX512-BF16, with recall within a few points of
    float32's; or ``bfloat16-fine``, only the decoder blocks that the finest level alone reads in
    bfloat16 (``UNet.fine_blocks``), the coarser levels exact: 0.84-0.88x, the same recall at every
    threshold on 159 queries of ten scenes, poses up to 0.4 mm and 0.3 deg from float32's; neither
    measured on CPUs without native bfloat16 (docs/benchmarks.md, "The CPU query at Cambridge settings")."""

    num_dbs: int = 5
    average_observations: bool = False
    num_iters: int = 100
    min_track_length: int = 3
    min_points: int = 10
    points_per_cell: float = 0.0
    network_precision: str = "float32"
    verification: VerificationConfig = field(default_factory=VerificationConfig)

    def __post_init__(self):
        if min(self.num_iters, self.min_track_length, self.min_points) < 1 or self.points_per_cell < 0:
            raise ValueError(f"num_iters, min_track_length and min_points must be at least 1 and points_per_cell not "
                             f"negative, not {self.num_iters}, {self.min_track_length}, {self.min_points} and "
                             f"{self.points_per_cell}.")
        if self.network_precision not in NETWORK_PRECISIONS:
            raise ValueError(f"network_precision must be one of {sorted(NETWORK_PRECISIONS)}, "
                             f"got {self.network_precision!r}.")


@dataclass
class LevelState:
    """A candidate while ``Localizer.localize_batch`` refines it: its observations and current pose
    ``T``, the reference features of the image scale being run (``refs``), whether it is still
    ``active``, its own seconds (``t_own``) and the result being filled; for a rival start, its
    query's own starts' poses at the end of each level (``own``: (image scale, level) -> 3 x 4 pose);
    the ``levels`` it is refined on; the 2D-3D matches that support its start (``keypoints``); the body it is
    refined with (``body``)."""

    query: QueryRecord
    rgb: Optional[np.ndarray]
    cache: QueryCache
    result: QueryResult
    active: bool = False
    t_own: float = 0.0
    obs: Optional[Observations] = None
    T: Optional[Pose] = None
    prior_T: Optional[Pose] = None
    refs: Optional[Tuple] = None
    own: Optional[List[Dict[Tuple[int, int], np.ndarray]]] = None
    levels: Sequence[int] = ()
    keypoints: Optional[Keypoints] = None
    body: Optional[BodyRef] = None


def own_solvers(solvers: Sequence[LevenbergMarquardt], compiled: bool) -> List[LevenbergMarquardt]:
    """Copies of ``solvers`` in eval mode that share their learned parameters (the damping) and have
    their own interpolator and kernels: the compiled ones (``pipeline.kernels``) or, with
    ``compiled`` False, the torch code. The solvers given are left as they are."""
    out = []
    for solver in solvers:
        mine = copy.copy(solver)  # a new attribute dict; parameters and submodules shared, as read
        mine.__dict__["training"] = False
        mine.__dict__["interpolator"] = copy.copy(solver.interpolator)
        mine.interpolator.tap_reducer = kernels.reduce_taps if compiled else None
        mine.__dict__["system_builder"] = kernels.build_system if compiled else None
        out.append(mine)
    return out


class Localizer:
    """Localizes queries against one map with one network and its per-level solvers."""

    def __init__(self, net: UNet, solvers: Sequence[LevenbergMarquardt], reader: MapReader,
                 conf: LocalizerConfig, device: str = "cpu", levels: Optional[Sequence[int]] = None,
                 scales: Optional[Sequence[int]] = None, max_points: Optional[int] = None,
                 finest_on_demand: bool = True, compiled_kernels: bool = True):
        """levels: the levels to optimise, e.g. (0, 1) for the paper's refinement mode; default all.
        scales: the image scales of the store to run (e.g. (1,)); default all, coarse to fine.
        max_points: a seeded subset of at most this many points per query (the search's coarse
        screening: at stride 16 many points share a feature-map cell). finest_on_demand: on CPU, a
        query's finest level is decoded where it is sampled (``pipeline.localization.finest``; the same
        maps there to float rounding), except under whole-network bfloat16; False, or on a GPU (where the
        pass is cheap and a tile request would wait for the device at every LM iteration): in the pass.
        compiled_kernels: on CPU, the solvers reduce the LM's taps and form its normal equations with the
        compiled kernels (``pipeline.kernels``; the same figures to float rounding) where numba is there;
        False: their torch code. The solvers given (a process's cached model's) are not changed: the
        localizer works with copies that share their learned parameters (``own_solvers``)."""
        compiled = compiled_kernels and kernels.available() and torch.device(device).type == "cpu"
        self.net, self.reader, self.conf, self.device = net, reader, conf, device
        self.solvers = own_solvers(solvers, compiled)
        self.max_points, self.finest_on_demand = max_points, finest_on_demand
        if levels is not None and not set(levels) <= set(range(len(net.strides))):
            raise ValueError(f"levels {list(levels)}: the network has levels 0 (finest) to {len(net.strides) - 1}.")
        self.levels = sorted(set(levels if levels is not None else range(len(net.strides))), reverse=True)
        stored = list(reader.conf.image_scales)
        missing = sorted(set(scales or ()) - set(stored))
        if missing:
            raise ValueError(f"Image scales {missing} are not in the store (it has {stored}).")
        self.scales = [k for k, s in enumerate(stored) if scales is None or s in scales]

    def reference_features(self, obs: Observations, scale: int, stats: Optional[Dict] = None,
                           levels: Optional[Sequence[int]] = None):
        """Points (K, 3) and per level (features (K, C) normalised, confidences (K,)) of the
        observations ``obs``; as the official localizer, an observation invalid at any of the
        optimised ``levels`` (default the localizer's) is dropped."""
        feats = self.reader.features(obs, scale)
        valid = np.logical_and.reduce([feats[level][2] for level in (self.levels if levels is None else levels)])
        if stats is not None:  # observations (not points) dropped as invalid at an optimised level
            stats[f"invalid_observations_s{scale}"] = int((~valid).sum())
        point = obs.point[valid]
        levels = [(f[valid], w[valid]) for f, w, _ in feats]
        levels = [(torch.from_numpy(f), torch.from_numpy(w)) for f, w in levels]
        if self.conf.average_observations:  # confidence-weighted mean, in float64 as the sums are long
            uniq, inverse = np.unique(point, return_inverse=True)
            index = torch.from_numpy(inverse.reshape(-1))
            count = torch.from_numpy(np.bincount(inverse, minlength=len(uniq))).double()
            averaged = []
            for f, w in levels:
                w = w.double()
                wsum = torch.zeros(len(uniq), dtype=torch.float64).index_add_(0, index, w)
                fsum = torch.zeros(len(uniq), f.shape[1], dtype=torch.float64).index_add_(
                    0, index, f.double() * w[:, None])
                averaged.append(((fsum / wsum[:, None]).float(), (wsum / count).float()))
            point, levels = uniq, averaged
        xyz = torch.from_numpy(self.reader.xyz[point]).float()
        return xyz, [(normalize(f.float(), dim=-1), w.float()) for f, w in levels]

    @torch.no_grad()
    def predict(self, rgb: np.ndarray, k: int):
        """Dense query prediction at image scale index k, and the resize factors."""
        resized, scales = resize_max(rgb, self.reader.conf.resize // self.reader.conf.image_scales[k])
        image = to_tensor(resized)[None].to(self.device)
        defer = self.finest_on_demand and self.conf.network_precision != "bfloat16" \
            and torch.device(self.device).type == "cpu"
        return predict_in_precision(self.net, image, self.conf.network_precision, defer_finest=defer), scales

    @torch.no_grad()
    def localize(self, query: QueryRecord, dbs: List[int], prior: np.ndarray,
                 rgb: Optional[np.ndarray] = None, cache: Optional[QueryCache] = None,
                 selected: Optional[np.ndarray] = None) -> QueryResult:
        """Refine ``prior`` against references ``dbs``; ``rgb`` and ``cache`` (``QueryCache``)
        let callers reuse the query image and predictions across hypotheses; ``selected``
        (K, 2) (point, reference) pairs restricts the observations (hloc PnP inliers)."""
        return self.localize_batch([Candidate(query, dbs, prior, rgb, cache, selected)])[0]

    @torch.no_grad()
    def localize_batch(self, candidates: List[Candidate]) -> List[QueryResult]:
        """Localize several candidates, solving each level as one LM batch per group of queries
        whose feature maps have the same shape and whose cameras the same model.

        Rival starts (``Candidate.rival``) run after the others, and only for a query with a
        verified start: ``check_rivals`` can reject nothing else. A rival stops at the end of a
        level before the last where it lies near one of its query's own starts at the end of that
        level (``_join_rivals``). The per-problem stopping rule of the solver makes the result of
        each query the same as localizing it alone. An error in one query (a bad reference block,
        a network error) fails that query with its reason, not the batch; an error in a group's
        solve fails that group's queries.
        """
        results: List[Optional[QueryResult]] = [None] * len(candidates)
        owns = [i for i, c in enumerate(candidates) if not (c.rival and c.cache is not None)]
        for i, r in zip(owns, self._refine([candidates[i] for i in owns])):
            results[i] = r
        verified = {candidates[i].query.name for i in owns if results[i].success}
        tracks: Dict[str, List[Dict]] = {}  # per verified query: its own starts' poses per level
        for i in owns:
            if candidates[i].query.name in verified:
                tracks.setdefault(candidates[i].query.name, []).append(
                    {(p["scale"], p["level"]): np.asarray(p["pose"]) for p in results[i].per_level if not p["failed"]})
        rivals = [i for i, r in enumerate(results) if r is None and candidates[i].query.name in verified]
        for i, r in zip(rivals, self._refine([candidates[i] for i in rivals],
                                             [tracks[candidates[i].query.name] for i in rivals])):
            results[i] = r
        for i, r in enumerate(results):
            if r is None:
                results[i] = self._unrefined(candidates[i])
                results[i].reason = f"{JOINED}none of its query's own starts was verified"
        return results

    def _unrefined(self, c: Candidate) -> QueryResult:
        """A candidate's result before refinement: its prior, references and notes."""
        return QueryResult(c.query.name, False, np.asarray(c.prior, np.float64), None,
                           [self.reader.names[i] for i in c.dbs], notes=list(c.query.notes))

    def _refine(self, candidates: List[Candidate], own: Optional[List[List[Dict]]] = None) -> List[QueryResult]:
        """``localize_batch`` for candidates of one kind: the query's own starts, or rival starts with
        their queries' own starts' poses per (image scale, level) (``own``)."""
        states = []
        for c in candidates:
            t_item = time.perf_counter()
            query = c.query
            result = self._unrefined(c)
            levels = self.levels if c.levels is None else sorted(set(c.levels) & set(self.levels) | {self.levels[-1]},
                                                                  reverse=True)
            st = LevelState(query, c.rgb, QueryCache() if c.cache is None else c.cache, result, levels=levels,
                            keypoints=c.keypoints, body=c.body)
            states.append(st)
            try:
                seen = self.reader.observations(c.dbs, 1, c.selected)
                keep = self.reader.track_length[seen.point] >= self.conf.min_track_length
                st.obs = Observations(seen.point[keep], seen.db[keep], seen.rows[keep])
                points = np.unique(st.obs.point)
                if self.max_points and len(points) > self.max_points:
                    chosen = np.random.default_rng(0).choice(points, self.max_points, replace=False)
                    sub = np.isin(st.obs.point, chosen)
                    st.obs = Observations(st.obs.point[sub], st.obs.db[sub], st.obs.rows[sub])
                result.num_points = int(len(np.unique(st.obs.point)))
                short = result.filters["short_tracks"] = int(len(np.unique(seen.point[~keep])))
                if result.num_points < self.conf.min_points:
                    result.reason = f"references see {result.num_points} points (< {self.conf.min_points})" + (
                        f"; {short} more are seen by fewer than {self.conf.min_track_length} map images "
                        "(--min-track-length)" if short else "")
                    continue
                if st.rgb is None:  # a library caller: the same read and size rule as a shard's
                    st.rgb, camera, note = read_image_for(query.path, query.camera)
                    if note:
                        st.query = dataclasses.replace(query, camera=camera)
                        result.notes.append(note)
                st.T = st.prior_T = Pose.from_matrix(c.prior).float()
                st.active = True
            except (ImageReadError, StoreReadError, ValueError) as e:
                result.reason = str(e)
            finally:
                st.t_own += time.perf_counter() - t_item
        for st, tracks in zip(states, own or ()):  # a rival start's siblings: its query's own starts
            st.own = tracks
        for k in self.scales:
            image_scale = self.reader.conf.image_scales[k]
            active = [st for st in states if st.active]
            for st in active:
                t_item = time.perf_counter()
                try:
                    # the starts of one query's search share its cache, references and points:
                    # their reference features are read and averaged once
                    obs = st.obs
                    key = ("refs", k, tuple(st.levels), hash((obs.point.tobytes(), obs.db.tobytes(),
                                                               obs.rows.tobytes())))
                    if key not in st.cache.references:
                        stats: Dict = {}
                        st.cache.references[key] = (self.reference_features(obs, k, stats, st.levels), stats)
                    st.refs, stats = st.cache.references[key]
                    st.result.filters.update(stats)
                    st.cache.network(k, lambda: self.predict(st.rgb, k))
                except (StoreReadError, ValueError, RuntimeError) as e:
                    self._fail(st, f"{type(e).__name__}: {e}" if not isinstance(e, StoreReadError) else str(e))
                # this query's own work at this scale: its reference features and its network pass
                st.result.timings[f"features_s{k}"] = time.perf_counter() - t_item
                st.t_own += time.perf_counter() - t_item
            groups: Dict[Tuple, List[LevelState]] = {}
            for st in active:
                if st.active:
                    key = (level_shape(st.cache.passes[k][0], 0), st.query.camera.to_pixloc().distortion)
                    groups.setdefault(key, []).append(st)
            split_bodies(groups)
            t0 = time.perf_counter()
            for level in self.levels:
                final = k == self.scales[-1] and level == self.levels[-1]
                for group in groups.values():
                    group = [st for st in group if st.active and level in st.levels]
                    if not group:
                        continue
                    try:
                        self._solve_level(group, k, image_scale, level, final)
                    except (ValueError, RuntimeError) as e:  # recorded per query, never dropped
                        logger.warning("LM batch of %d queries failed: %s", len(group), e)
                        for st in group:
                            self._fail(st, f"LM failed at image scale {image_scale}, level {level}: "
                                           f"{type(e).__name__}: {e}")
                if not final:
                    self._join_rivals(active, image_scale, level)
            # the LM solves the group as one batch: each query gets an equal share of its time
            t_optim = (time.perf_counter() - t0) / max(len(active), 1)
            for st in active:
                st.result.timings[f"optim_s{k}"] = t_optim
                st.t_own += t_optim
        for st in states:
            result = st.result
            if st.active:
                result.refined = st.T.to_matrix(orthonormal=True)
                result.confidence, reason = verify(result.evidence, self.conf.verification)
                result.success = reason is None
                result.reason = reason or ""
                kept = keep_start(result.evidence, self.conf.verification) if result.success else None
                if kept:  # the refinement left the keypoints' support: their pose is reported
                    result.refined = np.asarray(result.prior, np.float64)
                    result.notes.append(kept)
            result.timings["total"] = st.t_own  # its own work, plus its share of the batched LM
        return [st.result for st in states]

    def _join_rivals(self, states: List[LevelState], image_scale: int, level: int) -> None:
        """Stop the rival starts among ``states`` whose query's own starts had all stopped by the end
        of this level, or that lie within ``join`` x (``agree_t`` x the median point depth,
        ``agree_R``) of one of them there: from there both converge to one pose, which
        ``check_rivals`` would call agreeing."""
        conf = self.conf.verification
        for st in states if conf.join > 0 else ():
            if not (st.active and st.own is not None):
                continue
            own = [t[image_scale, level] for t in st.own if (image_scale, level) in t]
            if not own:
                st.active, st.result.reason = False, f"{JOINED}its query's own starts stopped before it"
                continue
            xyz = st.refs[0].detach().double().cpu().numpy()
            b = st.T.to_matrix(orthonormal=True)
            for a in own:
                depth = np.median(xyz @ a[2, :3] + a[2, 3]) if len(xyz) else np.nan
                dt, dR = relative_motion(a, b, float(depth) if np.isfinite(depth) and depth > 0 else 1.0)
                if dt <= conf.join * conf.agree_t and dR <= conf.join * conf.agree_R:
                    st.active, st.result.refined = False, b
                    st.result.reason = (f"{JOINED}it reached the query's start at image scale {image_scale}, "
                                        f"level {level} ({dR:.2f} deg, {dt:.3f} depths)")
                    break

    @staticmethod
    def _fail(st: LevelState, reason: str) -> None:
        st.active = False
        st.result.reason = reason

    def _subset(self, n: int, cells: int, level: int) -> Optional[torch.Tensor]:
        """The points LM uses at a level with ``cells`` feature-map cells (``points_per_cell``):
        None for all of them, else a seeded subset, sorted."""
        if self.conf.points_per_cell <= 0:
            return None
        keep = max(MIN_SUBSET, int(self.conf.points_per_cell * cells))
        if n <= keep:
            return None
        rng = np.random.default_rng(level)
        return torch.from_numpy(np.sort(rng.choice(n, keep, replace=False)))

    def _solve_level(self, group: List[LevelState], k: int, image_scale: int, level: int, final: bool) -> None:
        """One LM batch for ``group`` at one level; points are padded and masked to a common N.
        Records the evidence of the level's start and end poses (``pixloc.optim.evidence``) and, at the
        ``final`` level, the contrast and uncertainty of its end pose, for verification."""
        stride = self.net.strides[level]
        first = group[0].cache.passes[k][0]
        shape = level_shape(first, level)
        subsets = [self._subset(len(st.refs[0]), shape[-2] * shape[-1], level) for st in group]
        n_max = max(len(st.refs[0]) if sub is None else len(sub) for st, sub in zip(group, subsets))
        p3d, F_ref, W_ref, mask, cams = [], [], [], [], []
        # normalised features + confidence; a deferred finest level is decoded where it is sampled
        maps = new_query_maps((len(group),) + shape[1:], level_like(first, level), dtype=torch.float32)
        deferred = {b: st.cache.passes[k][0]["finest"] for b, st in enumerate(group)
                    if st.cache.passes[k][0]["features"][level] is None}
        for st, sub in zip(group, subsets):
            xyz, levels = st.refs
            f, w = levels[level]
            if sub is not None:
                xyz, f, w = xyz[sub], f[sub], w[sub]
            n = len(xyz)
            pad = n_max - n
            p3d.append(torch.cat([xyz, xyz.new_zeros(pad, 3)]))
            F_ref.append(torch.cat([f, f.new_zeros(pad, f.shape[1])]))
            W_ref.append(torch.cat([w, w.new_zeros(pad)]))
            mask.append(torch.arange(n_max) < n)
            pred, (sx, sy) = st.cache.passes[k]
            if len(cams) not in deferred:  # official: the dense map is L2-normalised (as F.normalize)
                write_level(maps[len(cams)], pred["features"][level][0],
                            pred["confidences"][level][0] if "confidences" in pred else None)
            cams.append(st.query.camera.to_pixloc(torch.float64).scale((sx / stride, sy / stride)).float())
        device = maps.device
        problem = FeaturemetricProblem(torch.stack(p3d).to(device), torch.stack(F_ref).to(device),
                                       maps[:, :-1], Camera.stack(cams).to(device),
                                       torch.stack(W_ref).to(device), maps[:, -1],
                                       torch.stack(mask).to(device), maps=maps,
                                       fill=FinestFill(maps, deferred) if deferred else None)
        T = Pose.stack([st.T for st in group]).to(device)
        keypoints = keypoint_term(group)
        solver = self.solvers[level]
        bodies = group_bodies(group)
        lm = solver(problem, T, num_iters=self.conf.num_iters, keypoints=keypoints, bodies=bodies)
        start = alignment_evidence(problem, T, solver.loss_fn, solver.interpolator)
        end = alignment_evidence(problem, lm.pose, solver.loss_fn, solver.interpolator)
        contrast = {}
        if final:
            contrast = {f"contrast_{px:g}px": alignment_contrast(problem, lm.pose, solver.loss_fn,
                                                                 solver.interpolator, px) for px in CONTRAST_SHIFTS}
            contrast.update(alignment_uncertainty(problem, lm.pose, solver.loss_fn, solver.interpolator,
                                                  bodies=bodies))
        for b, st in enumerate(group):
            failed = bool(lm.failed[b])
            result = st.result
            evidence = {f"{key}_{which}": float(ev[key][b]) for which, ev in (("start", start), ("end", end))
                        for key in ("inliers", "weighted_inliers", "valid", "cost")}
            result.per_level.append({"scale": int(image_scale), "level": level, "failed": failed,
                                     "pose": lm.pose[b].to_matrix(orthonormal=True).tolist(),
                                     "iterations": int(lm.iterations[b]), "residuals": int(mask[b].sum()),
                                     **evidence})
            result.iterations += int(lm.iterations[b])
            result.cost = float(lm.cost[b, int(lm.iterations[b]) - 1])
            if failed:
                result.reason = (f"LM failed at image scale {image_scale}, level {level} "
                                 f"({int(lm.num_valid[b])} valid points)")
                st.active = False
                continue
            st.T = lm.pose[b].cpu()
            if final:
                result.evidence = evidence_summary(result.per_level, {key: float(v[b]) for key, v in contrast.items()},
                    np.asarray(result.prior), st.T.to_matrix(orthonormal=True),
                    problem.p3d_world[b][problem.mask[b]].cpu().numpy())
                if st.keypoints is not None:  # how far the refined pose left the keypoints' support
                    one = keypoints.index(slice(b, b + 1))
                    result.evidence["keypoint_chi2"] = float(one.chi2(st.T[None]) - one.chi2(st.prior_T[None]))
                    result.evidence["keypoints"] = float(len(st.keypoints.xy))


def keypoint_term(group: List[LevelState]) -> Optional[KeypointTerm]:
    """The keypoint term of a batch (``pixloc.optim.keypoints``) where one of its candidates has keypoints:
    their reprojection in each query's own camera, padded to a common count (weight 0 where none)."""
    if all(st.keypoints is None for st in group):
        return None
    m = max(len(st.keypoints.xy) if st.keypoints is not None else 0 for st in group)
    B = len(group)
    p3d, p2d, mask = torch.zeros(B, m, 3), torch.zeros(B, m, 2), torch.zeros(B, m, dtype=torch.bool)
    scale, weight = torch.ones(B), torch.zeros(B)
    for b, st in enumerate(group):
        if st.keypoints is not None:
            k = st.keypoints
            n = len(k.xy)
            p3d[b, :n] = torch.from_numpy(np.asarray(k.xyz, np.float32))
            p2d[b, :n] = torch.from_numpy(np.asarray(k.xy, np.float32)) - 0.5  # pixloc's pixel centres
            mask[b, :n] = True
            scale[b], weight[b] = k.scale, k.weight
    cameras = Camera.stack([st.query.camera.to_pixloc() for st in group])
    return KeypointTerm(p3d, p2d, cameras, scale, mask, weight)


def evidence_summary(per_level: List[Dict], contrast: Dict[str, float],
                     prior: np.ndarray, refined: np.ndarray, p3d: np.ndarray) -> Dict[str, float]:
    """The evidence of a refinement, for ``verify``: at the finest level, the inlier fractions
    (plain and confidence-weighted), valid fraction and cost at the refined pose; the sharpness of the
    cost around the refined pose (``contrast_*px``); the motion from the prior and between the last two
    levels, the translations relative to the median depth of the points at the refined pose
    (scale-free). (The same figures at the prior, never read by ``verify``, are no longer recorded:
    at the finest level they cost a query the decoding of the tiles around the prior's projections.)"""
    last = per_level[-1]
    out = {f"{key}": last[f"{key}_end"] for key in ("inliers", "weighted_inliers", "valid", "cost")}
    out.update(contrast)
    depth = p3d @ refined[:, :3].T + refined[:, 3]
    depth = float(np.median(depth[:, 2])) if len(depth) else float("nan")
    scale = depth if np.isfinite(depth) and depth > 0 else 1.0
    out["depth"] = depth
    out["move_t"], out["move_R"] = relative_motion(prior, refined, scale)
    if len(per_level) > 1:
        out["last_t"], out["last_R"] = relative_motion(np.asarray(per_level[-2]["pose"]), refined, scale)
    else:
        out["last_t"], out["last_R"] = out["move_t"], out["move_R"]
    return out
