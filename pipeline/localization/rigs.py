"""Localizing a rig (its cameras at one instant) or a chunk of frames as one body.

Each image of a ``Frame`` is read and retrieves its own references, as a query alone does. The body
starts from each image's top-1 reference in turn, moved into the body's frame (body_from_world =
cam_from_body^-1 @ cam_from_world of that reference), so that a night or occluded camera can start from
where its day camera's retrieval puts the rig (starts that agree are all refined: leaving out those within
``agree_t`` x the depth and ``agree_R`` of an earlier one cost 7 points of recall on the beer sequence). From
each start,
every image is refined against its own references, all images of the frame as one pose
(``pixloc.optim.bodies``), batched with the other frames and starts; each image's evidence is read at its
camera's pose (``pipeline.localization.verify``).

The frame keeps the start verified by the rule (``BODY_RULES``; ties: the most images verified, the higher
confidence, the start of the most similar retrieval). By default (``half``) a frame is verified when at least
half of the images refined from that start are verified there: one image of a wrong pose can be sharp by
chance (on the real sequences, 3 of the 4 chunks verified wrong by ``any`` image had 1 or 2 of 5 verified),
and pooling the images' evidence into one verdict (``pooled``: the body's own uncertainty from its cameras'
summed information) verified the chunks that stay at a neighbouring view on a ring of views (28 wrong images
of 84 verified, against 4 of 51 with ``half``; docs/benchmarks.md, "Sequences"). A frame is rejected as
ambiguous where another start is verified too, by as many images, at a body pose that does not agree with it
(``agree_t`` x the median point depth, ``agree_R``), with both starts named. Each image
reports the body's pose through its camera, the images that could not be refined (too few points of their
own) included: that is what a rig is for. The images' own verdicts are kept in their notes. A frame of N
images costs N starts of N images, N^2 image refinements (the network pass and the references' features of
an image are shared by its starts).
"""

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np

from pixloc.geometry import relative_motion

from pipeline.localization.candidates import BodyRef, Candidate, QueryCache, QueryResult
from pipeline.localization.priors import NO_MATCH, failure
from pipeline.localization.refine import Localizer
from pipeline.localization.verify import VerificationConfig, verify
from pipeline.localization.retrieval import Retrieved, retrieve
from pipeline.localization.bodies import Frame, compose, invert
from pipeline.localization.query_image import describer, read_query
from pipeline.queries import QueryRecord
from pipeline.store.reader import MapReader

logger = logging.getLogger(__name__)
# when a body is verified at its pose: ``pooled``, its evidence pooled over its images (``body_evidence``) passes
# verification; ``half``, at least half of its refined images are verified alone; ``any``, one of them is
BODY_RULES = ("pooled", "half", "any")


@dataclass
class FrameResult:
    """A frame's outcome: its images' results (``images``, in the frame's order), the body's pose
    (body_from_world, 3 x 4: refined where verified, else its start), whether it is verified, the
    reason where not, the image it started from (``start``) and the images verified at the body's pose."""

    key: str
    images: List[QueryResult]
    pose: Optional[np.ndarray]
    success: bool
    reason: str = ""
    start: str = ""
    verified_by: List[str] = field(default_factory=list)
    confidence: float = 0.0


def _prepare(job, reader: MapReader, localizer: Localizer, query: QueryRecord):
    """An image's read, camera check and retrieval: (query, rgb, cache, Retrieved) or a failure (QueryResult)."""
    query, rgb, reason = read_query(query)
    if reason:
        return failure(query, reason)
    cache = QueryCache()
    r: Retrieved = retrieve(job.retrieval, reader, query, describer(reader, localizer, rgb, cache))
    if not r.dbs:
        return failure(query, NO_MATCH)
    return query, rgb, cache, r


def _similarity(r: Retrieved) -> float:
    return float(r.similarity[0]) if r.similarity is not None and len(r.similarity) else float("-inf")


def localize_frames(job, reader: MapReader, localizer: Localizer, frames: Sequence[Frame],
                    rule: str = "half") -> List[FrameResult]:
    """Localize each frame as one body (see the module docstring); the frames' LM problems are batched. ``job``:
    the run's ``LocalizationJob`` (its retrieval and number of references); ``rule``: when a body is verified
    (``BODY_RULES``)."""
    if rule not in BODY_RULES:
        raise ValueError(f"rule {rule!r}: one of {', '.join(BODY_RULES)}")
    candidates: List[Candidate] = []
    plans = []  # per frame: its images' failures, and per start (its image, body pose, per image a slot)
    for frame in frames:
        prepared = []
        for q in frame.queries:
            try:
                prepared.append(_prepare(job, reader, localizer, q))
            except (OSError, ValueError, RuntimeError) as e:  # recorded, never dropped
                logger.warning("Query %s failed: %s", q.name, e)
                prepared.append(failure(q, f"{type(e).__name__}: {e}"))
        ready = [i for i, p in enumerate(prepared) if not isinstance(p, QueryResult)]
        runs = []
        for s, o in enumerate(sorted(ready, key=lambda i: -_similarity(prepared[i][3]))):  # stable: ties in order
            body = compose(invert(frame.cam_from_body[o]), reader.cam_from_world[prepared[o][3].dbs[0]])
            slots = []
            for i, p in enumerate(prepared):
                if isinstance(p, QueryResult):
                    slots.append(p)
                    continue
                query, rgb, cache, r = p
                C = np.asarray(frame.cam_from_body[i], np.float64)
                slots.append(len(candidates))
                candidates.append(Candidate(query, list(r.dbs[:job.localizer.num_dbs]), compose(C, body), rgb, cache,
                                            origin=f"the top-1 reference of {frame.queries[o].name}",
                                            body=BodyRef(f"{frame.key}#{s}", C)))
            runs.append((o, body, slots))
        plans.append((prepared, runs))
    results = localizer.localize_batch(candidates) if candidates else []
    return [_finish(frame, prepared, runs, results, localizer.conf.verification, rule)
            for frame, (prepared, runs) in zip(frames, plans)]


@dataclass
class _Run:
    """One start of a frame after refinement: the image it came from, its body pose at the start and at the end,
    its images' results, those refined and those verified, its confidence."""

    origin: int
    start: np.ndarray
    body: np.ndarray
    images: List[QueryResult]
    refined: List[int]
    verified: List[int]
    confidence: float
    evidence: Dict[str, float] = field(default_factory=dict)
    verdict: Optional[str] = "not refined"


def body_evidence(images: List[QueryResult], refined: List[int]) -> Dict[str, float]:
    """The evidence of a body at its pose, for ``verify``: its refined images' 3 px contrast and fraction of points
    in view, averaged with their points as weights; the body's own uncertainty (``body_sigma``: its cameras'
    information summed, ``pixloc.optim.evidence.alignment_uncertainty``); the motion from the start, the last
    level's turn and the depth, as the median over its images."""
    ev = [images[i].evidence for i in refined if images[i].evidence]
    if not ev:
        return {}
    points = np.array([max(images[i].num_points, 1) for i in refined if images[i].evidence], np.float64)
    valid = np.array([e.get("valid", 0.0) for e in ev])
    out = {key: float(np.median([e.get(key, np.nan) for e in ev]))
           for key in ("move_t", "move_R", "last_t", "last_R", "depth")}
    seen = points * valid
    out["contrast_3px"] = float(np.average([e.get("contrast_3px", 0.0) for e in ev], weights=seen)) \
        if seen.sum() > 0 else 0.0
    out["valid"] = float(np.average(valid, weights=points))
    for key in ("sigma", "sigma_t", "sigma_R"):
        out[key] = float(ev[0].get(f"body_{key}", ev[0].get(key, np.nan)))
    return out


def _run(frame: Frame, origin: int, start: np.ndarray, slots, results: List[QueryResult], rule: str,
         conf: VerificationConfig) -> _Run:
    """One start's outcome, with its verdict by ``rule`` (``BODY_RULES``): None where verified, else why not."""
    images = [s if isinstance(s, QueryResult) else results[s] for s in slots]
    refined = [i for i, r in enumerate(images) if r.refined is not None and not isinstance(slots[i], QueryResult)]
    C = [np.asarray(c, np.float64) for c in frame.cam_from_body]
    body = compose(invert(C[refined[0]]), images[refined[0]].refined) if refined else start
    run = _Run(origin, start, body, images, refined, [i for i in refined if images[i].success],
               max((images[i].confidence for i in refined), default=0.0))
    if rule == "pooled" and refined:
        run.evidence = body_evidence(images, refined)
        run.confidence, run.verdict = verify(run.evidence, conf)
    elif refined:
        enough = len(run.verified) * 2 >= len(refined) if rule == "half" else bool(run.verified)
        run.verdict = None if enough else (
            f"rejected: {len(run.verified)} of the {len(refined)} images refined are verified at the body's pose"
            + (" (at least half must be)" if rule == "half" else ""))
    return run


def _agree(a: np.ndarray, b: np.ndarray, depth: float, conf: VerificationConfig) -> bool:
    """Two body poses within ``agree_t`` x ``depth`` and ``agree_R`` of each other."""
    dt, dR = relative_motion(a, b, depth)
    return dt <= conf.agree_t and dR <= conf.agree_R


def _disagreement(frame: Frame, best: _Run, runs: List[_Run], conf: VerificationConfig) -> str:
    """Why the best start is ambiguous: another start verified too, by as many images, at a body pose that does not
    agree with it (``agree_t`` x the median point depth, ``agree_R``); else ""."""
    depth = float(np.nanmedian([best.images[i].evidence.get("depth", np.nan) for i in best.refined]))
    depth = depth if np.isfinite(depth) and depth > 0 else 1.0
    for other in runs:
        if other is best or other.verdict is not None or len(other.verified) < len(best.verified):
            continue
        if not _agree(best.body, other.body, depth, conf):
            dt, dR = relative_motion(best.body, other.body, depth)
            return (f"rejected: ambiguous: the starts from {frame.queries[best.origin].name} and "
                    f"{frame.queries[other.origin].name} are both verified, by {len(best.verified)} images each, at "
                    f"body poses {dt:.2f} depths and {dR:.1f} deg apart")
    return ""


def _finish(frame: Frame, prepared, runs, results: List[QueryResult], conf: VerificationConfig,
            rule: str) -> FrameResult:
    """A frame's verdict from its starts' results, and each image's reported pose (see the module docstring)."""
    if not runs:
        reason = "no image of the frame could be refined: " + "; ".join(f"{r.name}: {r.reason}" for r in prepared)
        body = {"key": frame.key, "pose": None, "success": False, "images": [q.name for q in frame.queries],
                "start": None, "verified_by": []} if frame.tags else {}
        return FrameResult(frame.key, [dataclasses.replace(r, body=body) for r in prepared], None, False, reason)
    done = [_run(frame, o, start, slots, results, rule, conf) for o, start, slots in runs]
    best = max(done, key=lambda r: (r.verdict is None, len(r.verified), r.confidence))  # ties: the earlier start
    reason = _disagreement(frame, best, done, conf) if best.verdict is None else ""
    success = best.verdict is None and not reason
    if best.verdict is not None:
        reason = (f"{best.verdict}; " if best.refined else "the body was not refined: ") + "; ".join(
            f"{r.name}: {r.reason or 'verified'}" for r in best.images)
    Cs = [np.asarray(C, np.float64) for C in frame.cam_from_body]
    pose = best.body if success else best.start
    body = {"key": frame.key, "pose": pose.tolist(), "success": success, "images": [q.name for q in frame.queries],
            "start": frame.queries[best.origin].name, "verified_by": [best.images[i].name for i in best.verified]}
    body = body if frame.tags else {}  # an untagged frame of one image is a query alone: no body in its record
    images = []
    for i, r in enumerate(best.images):
        own = "verified" if i in best.verified else (r.reason or "not refined")
        note = (f"body {frame.key}: {len(frame.queries)} images refined as one pose, from {len(done)} starts; the "
                f"best from {frame.queries[best.origin].name}'s retrieval; this image alone: {own}")
        images.append(dataclasses.replace(
            r, success=success, refined=compose(Cs[i], best.body) if best.refined else None,
            prior=compose(Cs[i], best.start), confidence=best.confidence, reason=reason, notes=list(r.notes) + [note],
            body=body))
    return FrameResult(frame.key, images, pose, success, reason,
                       frame.queries[best.origin].name, [images[i].name for i in best.verified], best.confidence)
