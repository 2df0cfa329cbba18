"""Wide-basin search (the ``search`` prior): many starting poses, screened at the coarsest level.

PixLoc's LM converges only inside a basin around the true pose; a retrieved reference's pose
can lie outside it (metres and tens of degrees off). The top-1 reference's pose is refined first;
where that refinement is verified, it stands. Elsewhere the search starts from the poses of the
top retrieved references and from perturbations of each (turns left/right and up/down about
the camera centre, moves forward/backward along the viewing direction, scaled to the scene by
the reference's median point depth), runs only the coarsest level for all of them as one LM
batch, keeps the best few per query (the lowest coarse cost among the starts that keep the
points in view), and refines those through every level. All hypotheses of a query use the same
references, hence the same points and features, so their coarse costs and their verification
confidences (the sharpness of the cost, ``pipeline.localization.verify``; it picks the winner) compare like
with like.
"""

import dataclasses
from dataclasses import dataclass
from typing import List, Sequence, Tuple

import numpy as np

from pixloc.geometry import relative_motion

from pipeline.localization.refine import JOINED, Candidate, Localizer, QueryResult
from pipeline.localization.verify import NOT_PINNED, VerificationConfig
from pipeline.store.reader import MapReader


RANKS = ("cost", "confidence")
RIVAL = "rival: "  # the label of a rival start (``rival_starts``)
AMBIGUOUS = "rejected: ambiguous: "  # the reason of a verified pose that a rival contradicts (``check_rivals``)


@dataclass(frozen=True)
class SearchConfig:
    """references: top retrieved references whose poses seed hypotheses; yaw, pitch: +- turns
    (degrees) about the camera's vertical and horizontal axes; shift: +- moves along the viewing
    direction, as a fraction of the reference's median point depth; keep: the starts per query,
    besides the top-1 and average poses, refined through the finer levels after the coarse screening
    (the best by ``rank``). rank: ``cost``, the lowest mean robust cost at the coarsest level among
    the starts that keep at least ``min_valid`` of the screening points in view (then the others, by
    cost; every start of a query is screened on the same points), or ``confidence``, the coarse
    verification confidence (the choice before: on virtual_gallery and Sacre Coeur it ranked the
    start nearest the truth 18th and 7th of 28, the cost 1st). iters, max_points: LM iterations
    and points (a seeded subset) of the screening (256: the same recall as 1,024 on the seven
    scenes of ``pixloc benchmark search``, at 0.6x the search's time on 7-Scenes). average: the
    pose averaged over the references' covisibility cluster (the ``average`` prior) is one more
    start, with its perturbations. The top-1 reference's pose and the average pose always go on
    to the finer levels (then the search loses nothing where ``top1`` or ``average`` converge),
    besides the ``keep`` best other starts.
    merge_t, merge_R: two of these whose coarse poses lie within ``merge_t`` x the top reference's
    median point depth and ``merge_R`` degrees of each other sit in one basin, and only the first
    (top-1, average, then the others) is refined (0: only identical poses). first: the top-1 start
    is refined through every level first, as the ``top1`` prior does, and the other starts are
    screened and refined only for the queries where that refinement is not verified (a verified
    top-1 refinement is kept: the search costs nothing where ``top1`` succeeds)."""

    references: int = 3
    yaw: float = 15.0
    pitch: float = 10.0
    shift: float = 0.25
    keep: int = 1
    rank: str = "cost"
    min_valid: float = 0.5
    iters: int = 15
    max_points: int = 256
    average: bool = True
    merge_t: float = 0.02
    merge_R: float = 1.0
    first: bool = True

    def validate(self) -> None:
        if min(self.references, self.keep, self.iters, self.max_points) < 1:
            raise ValueError("search: references, keep, iters and max_points must be at least 1.")
        if min(self.yaw, self.pitch, self.shift, self.merge_t, self.merge_R) < 0:
            raise ValueError("search: yaw, pitch, shift, merge_t and merge_R must not be negative.")
        if self.rank not in RANKS:
            raise ValueError(f"search: rank must be one of {', '.join(RANKS)}, not {self.rank!r}.")
        if not 0 <= self.min_valid <= 1:
            raise ValueError(f"search: min_valid must lie in [0, 1], not {self.min_valid}.")

    def size(self) -> int:
        """Hypotheses per reference."""
        return 1 + 2 * (self.yaw > 0) + 2 * (self.pitch > 0) + 2 * (self.shift > 0)


def _turn(axis: int, degrees: float) -> np.ndarray:
    a = np.deg2rad(degrees)
    c, s = np.cos(a), np.sin(a)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def perturbations(T: np.ndarray, depth: float, conf: SearchConfig) -> List[Tuple[np.ndarray, str]]:
    """(cam_from_world, label) of the pose ``T`` and its perturbations. Turns keep the camera
    centre (R' = dR R, t' = dR t); a shift by d moves the centre along the optical axis (t' = t - d z)."""
    T = np.asarray(T, np.float64)
    out = [(T, "reference")]
    for axis, angle, name in ((1, conf.yaw, "yaw"), (0, conf.pitch, "pitch")):
        if angle > 0:
            for sign in (1, -1):
                dR = _turn(axis, sign * angle)
                out.append((np.concatenate([dR @ T[:, :3], (dR @ T[:, 3])[:, None]], 1),
                            f"{name} {sign * angle:+g} deg"))
    if conf.shift > 0:
        for sign in (1, -1):
            d = sign * conf.shift * depth
            out.append((np.concatenate([T[:, :3], (T[:, 3] - np.array([0.0, 0.0, d]))[:, None]], 1),
                        f"{'forward' if d > 0 else 'backward'} {abs(d):.3g}"))
    return out


def median_depth(reader: MapReader, i: int) -> float:
    """Median depth of the points that reference image ``i`` observes (1 if it sees none)."""
    obs = reader.observations([i], 1)
    if not len(obs.point):
        return 1.0
    T = reader.cam_from_world[i]
    z = reader.xyz[np.unique(obs.point)] @ T[2, :3] + T[2, 3]  # depth along the optical axis
    z = z[z > 0]
    return float(np.median(z)) if len(z) else 1.0


def hypotheses(reader: MapReader, dbs: List[int], conf: SearchConfig, average=None
               ) -> List[Tuple[np.ndarray, str]]:
    """Starting poses from the top ``conf.references`` of ``dbs`` (retrieval order), labelled
    ``NAME: reference`` for a reference's own pose; then from ``average`` (a pose, with the
    median depth of the top reference) if given."""
    out = []
    for i in dbs[:conf.references]:
        depth = median_depth(reader, i)
        out += [(T, f"{reader.names[i]}: {label}") for T, label in perturbations(reader.cam_from_world[i], depth, conf)]
    if average is not None:
        depth = median_depth(reader, dbs[0])
        out += [(T, f"average: {label}") for T, label in perturbations(average, depth, conf)]
    return out


def same_basin(a: np.ndarray, b: np.ndarray, depth: float, conf: SearchConfig) -> bool:
    """Whether two coarse poses (cam_from_world) lie within ``conf.merge_t`` x ``depth`` (camera
    centres) and ``conf.merge_R`` degrees of each other."""
    dt, dR = relative_motion(a, b, depth)
    return dt <= conf.merge_t and dR <= conf.merge_R


def screening_order(results: List[QueryResult], conf: SearchConfig, skip=()) -> List[int]:
    """Indices of the screened starts that converged (``results``, coarse), best first, by
    ``conf.rank`` (see ``SearchConfig``; ``cost``: ties by confidence), leaving out ``skip``."""
    if conf.rank == "confidence":
        return [j for j in rank_results(results) if j not in skip]
    done = [j for j, r in enumerate(results) if r.refined is not None and r.evidence and j not in skip]
    return sorted(done, key=lambda j: (results[j].evidence["valid"] < conf.min_valid, results[j].evidence["cost"],
                                       -results[j].confidence))


class Hypotheses(list):
    """The candidates of one query's search (``pipeline.localization.refine.Candidate``, each labelled by its
    ``origin``); after the screening, also the top-1 start's pose (the prior a rejected search
    reports) and how many were screened; ``always``: the starts refined whatever the screening
    ranks them; ``depth``: the top reference's median point depth (the scale of the scene);
    ``merged``: kept starts left out as duplicates; ``first``: the top-1 start's refinement through
    every level when it ran before the search."""

    def __init__(self, candidates, top1=None, screened=None, always=(0,), depth=1.0, merged=0, first=None,
                 first_label=None):
        super().__init__(candidates)
        self.top1, self.screened, self.always = top1, screened, list(always)
        self.depth, self.merged = depth, merged
        self.first, self.first_label = first, first_label  # the top-1 start's full refinement, if done first

    @property
    def labels(self) -> List[str]:
        return [c.origin for c in self]


def solve(localizer: Localizer, prepared: List) -> List[Tuple]:
    """(prepared, its results) per query: one localize_batch for every query's candidates; a
    failure (QueryResult) comes with None."""
    candidates = [c for p in prepared if isinstance(p, list) for c in p]
    solved = iter(localizer.localize_batch(candidates)) if candidates else iter(())
    return [(p, None if isinstance(p, QueryResult) else [next(solved) for _ in p]) for p in prepared]


def rank_results(results: List[QueryResult]) -> List[int]:
    """Indices of the refined results, best first: verification confidence, then the
    confidence-weighted inlier fraction."""
    done = [j for j, r in enumerate(results) if r.refined is not None and r.evidence]
    return sorted(done, key=lambda j: (results[j].confidence, results[j].evidence["weighted_inliers"]), reverse=True)


def refine_and_pick(localizer: Localizer, prepared: List) -> List[Tuple]:
    """Refine every query's candidates through every level (one batch: ``solve``) and pick its result:
    (prepared, its refined candidates, their start labels, the index of the result) per query, or
    (the failure, None, None, None). The result is the best of the query's own starts (``rank_results``,
    a verified one first; with a search's top-1 refinement, if it ran first), checked against all the
    others (``check_rivals``): its rival starts (``rival_starts``, labelled ``RIVAL``...) and a search's
    other starts."""
    out = []
    for p, candidates in solve(localizer, prepared):
        if candidates is None:
            out.append((p, None, None, None))
            continue
        labels, own = [c.origin for c in p], sum(not c.rival for c in p)  # rivals come last (rival_starts)
        if isinstance(p, Hypotheses) and p.first is not None:  # the top-1 start, refined before the search
            candidates, labels, own = [p.first] + candidates, [p.first_label] + labels, own + 1
        ranked = rank_results(candidates[:own])
        # the best verified one (a top-1 refinement rejected as ambiguous keeps its confidence), else the best
        j = next((i for i in ranked if candidates[i].success), ranked[0] if ranked else 0)
        check_rivals(candidates[j], [(labels[i], c) for i, c in enumerate(candidates) if i != j],
                     localizer.conf.verification)
        out.append((p, candidates, labels, j))
    return out


def top1_first(localizer: Localizer, prepared: List, conf: SearchConfig) -> List:
    """With ``conf.first``: refine every query's top-1 start through every level, with its rival
    starts (``rival_starts``), as one batch; a verified refinement that no rival contradicts is the
    query's result, the others go on to the search with it."""
    if not conf.first:
        return prepared
    searches = [k for k, p in enumerate(prepared) if isinstance(p, Hypotheses)]
    batches = [[prepared[k][0]] + rival_starts(localizer.reader, prepared[k][:1], localizer.conf.verification)
               for k in searches]
    solved = iter(localizer.localize_batch([c for b in batches for c in b]) if searches else ())
    out = list(prepared)
    for k, batch in zip(searches, batches):
        p, result = prepared[k], next(solved)
        check_rivals(result, [(c.origin, next(solved)) for c in batch[1:]], localizer.conf.verification)
        if result.success:
            result.notes.append(f"search: the top-1 start was verified (confidence {result.confidence:.2f}); "
                                f"the other {len(p) - 1} starts were not needed")
            out[k] = result
        else:
            p.first, p.first_label = result, p.labels[0]
    return out


def rival_starts(reader: MapReader, starts: Sequence[Candidate], conf: VerificationConfig) -> List[Candidate]:
    """Rival starts (``check_rivals``) for a query whose starts are the map's own poses: the poses of
    its next references (``starts[0].dbs``, in retrieval order) that are none of ``starts``' poses, at
    most ``conf.rivals``; against the same references, sharing the query's image and cache. (A rival
    next to the start converges with it and checks little; one that ends at the same pose agrees.
    A rival stops at a coarser level where it has joined one of the query's own starts:
    ``Localizer.localize_batch``.)"""
    if not conf.enabled or conf.rivals == 0 or not starts:
        return []
    first = starts[0]
    others = [i for i in first.dbs if not any(np.array_equal(reader.cam_from_world[i], c.prior) for c in starts)]
    return [dataclasses.replace(first, prior=np.asarray(reader.cam_from_world[i], np.float64),
                                origin=f"{RIVAL}reference {reader.names[i]}", rival=True)
            for i in others[:conf.rivals]]


def check_rivals(result: QueryResult, rivals: List[Tuple[str, QueryResult]], conf: VerificationConfig) -> None:
    """Reject a verified ``result`` as ambiguous where one of ``rivals`` ((its start's label, its
    refinement) of the same query, against the same references) is verified too at another pose:
    beyond ``conf.agree_t`` x the median point depth or ``conf.agree_R`` degrees. A note per rival. A
    rival rejected as ambiguous itself (a search's top-1 start), or as not pinned down (``max_sigma``:
    its cost is sharp for image shifts there, a minimum all the same), counts as verified. A rival start
    (``rival_starts``) whose cost is ``conf.sharper_by`` times less sharp than the result's (the 3 px
    contrast) does not reject it: the two poses are not equally supported. The search's other starts
    still do: among its perturbed starts, a verified pose far away marks a repeated structure however
    sharp the winner (measured: docs/verification.md, "Rival starts").

    Where the map's images lie a few degrees apart around an object or along a repeated facade, the
    refinement from a reference's pose can stay there, as sharp as at the truth, and be verified; the
    next reference's pose then stays at *its* place, verified too. Neither can be told from the
    other: both are left out (docs/verification.md, "Rival starts")."""
    if not result.success or not rivals:
        return
    depth = float(result.evidence.get("depth", float("nan")))
    depth = depth if np.isfinite(depth) and depth > 0 else 1.0
    for label, rival in rivals:
        name = label[len(RIVAL):] if label.startswith(RIVAL) else label
        if rival.reason.startswith(JOINED):  # stopped early (Localizer._join_rivals)
            result.notes.append(f"rival start {name}: {rival.reason[len(JOINED):]}")
            continue
        # a pose rejected as ambiguous was verified too; one not pinned down is sharp there all the same
        if not (rival.success or rival.reason.startswith((AMBIGUOUS, NOT_PINNED))):
            result.notes.append(f"rival start {name}: not verified ({rival.reason or 'failed'})")
            continue
        dt, dR = relative_motion(rival.refined, result.refined, depth)
        if dt <= conf.agree_t and dR <= conf.agree_R:
            result.notes.append(f"rival start {name}: converged to the same pose ({dR:.2f} deg, {dt:.3f} depths)")
            continue
        ours, theirs = (float(r.evidence.get("contrast_3px", float("nan"))) for r in (result, rival))
        if label.startswith(RIVAL) and conf.sharper_by > 0 and theirs > 0 and ours >= conf.sharper_by * theirs:
            result.notes.append(f"rival start {name}: verified too, {dR:.1f} deg and {dt:.2f} scene depths away, "
                                f"but its cost is {ours / theirs:.1f} times less sharp (contrast {theirs:.3f} "
                                f"against {ours:.3f})")
            continue
        result.success = False
        result.reason = (f"{AMBIGUOUS}the start from {name} is verified too (confidence "
                         f"{rival.confidence:.2f}) at a pose {dR:.1f} deg and {dt:.2f} scene depths away")
        return


def screen(localizer: Localizer, reader: MapReader, prepared: List, conf: SearchConfig) -> List:
    """Screen every query's starting poses at the coarsest level (one batch), and replace them by
    the ``conf.keep`` best coarse results (by ``conf.rank``), to be refined through every level."""
    coarse = Localizer(localizer.net, localizer.solvers, reader,
                       dataclasses.replace(localizer.conf, num_iters=conf.iters),
                       localizer.device, levels=[localizer.levels[0]],
                       scales=[reader.conf.image_scales[localizer.scales[0]]], max_points=conf.max_points)
    out = []
    for p, results in solve(coarse, prepared):
        if results is None:
            out.append(p)
            continue
        # the top-1 reference's pose and the average pose go on (so the search loses nothing where top1
        # or average converge), with the best others by the screening rank (search.rank)
        own = [j for j in p.always if results[j].refined is not None]
        candidates = own + screening_order(results, conf, skip=own)[:conf.keep]
        if not candidates:  # no start converged at the coarsest level: the top-1 start fails with its reason
            out.append(p.first if p.first is not None else results[0])
            continue
        kept = []  # starts whose coarse poses share a basin with one kept before are refined once
        for j in candidates:
            if not any(same_basin(results[j].refined, results[i].refined, p.depth, conf) for i in kept):
                kept.append(j)
        merged = len(candidates) - len(kept)
        if p.first is not None and kept and kept[0] == 0:  # the top-1 start: refined already
            kept = kept[1:]
        out.append(Hypotheses([dataclasses.replace(p[j], prior=results[j].refined) for j in kept],
                              top1=p[0].prior, screened=len(p), merged=merged, first=p.first,
                              first_label=p.first_label))
    return out
