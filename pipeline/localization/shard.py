"""Localization of one shard of queries: retrieval, pose prior, refinement, records.

A shard writes its records once, atomically, so a rerun skips finished shards.
Every query gets exactly one record; a query that cannot be localized gets
``success: false`` and a reason, and keeps its prior when it has one.
"""

import dataclasses
import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from pipeline.mapping.features import FeatureConfig, global_descriptor
from pipeline.images import ImageReadError, read_image_for
from pipeline.localization.refine import Localizer, LocalizerConfig, QueryResult
from pipeline.store.reader import MapReader, open_reader
from pipeline.models import localization_model
from pipeline.localization.priors import PRIORS as PRIOR_FUNCTIONS, Prepared, Start, failure, poses_file
from pipeline.queries import QueryRecord
from pipeline.localization.results import read_records, result_to_record, write_records
from pipeline.localization.retrieval import RETRIEVERS, RetrievalConfig, pairs_file, retrieve
from pipeline.localization.sift import SiftConfig
from pipeline.localization.search import Hypotheses, SearchConfig, refine_and_pick, rival_starts, screen, top1_first
from pipeline.runtime import keep_freed_memory, torch_threads
from pipeline.store.layout import StoreError
from pipeline.textfiles import InputError, write_atomic

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class LocalizationJob:
    """All a worker needs to localize a shard (picklable, recorded with the outputs).

    prior: ``top1``, ``average`` (covisibility cluster, similarity-weighted), or
    ``hypotheses`` (each of the top ``num_hypotheses`` reference poses refined; the
    highest verification confidence wins), or ``search`` (the top references' poses, the
    ``average`` pose, and perturbations of each, screened at the coarsest level; the top-1 and
    average poses and the ``search.keep`` best others refined, the most confident wins:
    ``pipeline.localization.search``), or ``poses`` (refinement mode: the poses of
    another pipeline, file ``prior_poses`` in the visuallocalization.net format), or
    ``hloc`` (refinement mode as the paper's: the PnP poses of an hloc ``_logs.pkl``,
    file ``hloc_logs``; its references reranked by PnP inliers, those with more than
    ``min_matches_db`` kept; queries with fewer than ``min_inliers`` inliers fail).
    point_selection (``hloc`` prior): ``all`` points of the kept references, ``inliers``
    (the PnP inliers only, observed by the references that matched them) or ``matched``
    (all 2D-3D matches). The store must be built from the SfM model hloc used.
    levels: optimise only these levels (the paper's refinement mode uses the two
    finest, (0, 1)); default all. scales: run only these of the store's image scales
    (e.g. (1,) of a [4, 1] store: refinement mode runs the full resolution only).
    """

    store: str
    features: FeatureConfig
    model: str
    localizer: LocalizerConfig
    retrieval: RetrievalConfig
    prior: str = "top1"
    num_hypotheses: int = 3
    device: str = "cpu"
    prior_poses: Optional[str] = None
    levels: Optional[Tuple[int, ...]] = None
    hloc_logs: Optional[str] = None
    point_selection: str = "all"
    min_matches_db: int = 10
    min_inliers: int = 10
    scales: Optional[Tuple[int, ...]] = None
    search: SearchConfig = SearchConfig()
    sift: SiftConfig = SiftConfig()

    def to_dict(self) -> Dict:
        """The job as recorded in job.json (and compared by reruns); the search and SIFT settings
        only with the priors that read them (``sift`` falls back to the search), the network's
        precision only where it is not the default."""
        d = asdict(self)
        if self.localizer.network_precision == "float32":  # as runs before the option recorded it
            del d["localizer"]["network_precision"]
        if self.prior not in ("search", "sift"):
            del d["search"]
        if self.prior != "sift":
            del d["sift"]
        return d

    def validate(self) -> None:
        """Refuse a job that cannot run, before any query does: unknown prior, retrieval method
        or point selection, options that do not go together, missing input files."""
        if self.prior not in PRIORS:
            raise ValueError(f"Unknown prior {self.prior!r}: use one of {', '.join(PRIORS)}.")
        method = self.retrieval.method
        if method not in RETRIEVAL_METHODS:
            raise ValueError(f"Unknown retrieval method {method!r}: use one of {', '.join(RETRIEVAL_METHODS)}.")
        if self.point_selection not in POINT_SELECTIONS:
            raise ValueError(f"Unknown point selection {self.point_selection!r}: use one of "
                             f"{', '.join(POINT_SELECTIONS)}.")
        if self.point_selection != "all" and self.prior != "hloc":
            raise ValueError(f"Point selection {self.point_selection!r} needs the hloc prior (the inliers come "
                             "from its logs); use --point-selection all with other priors.")
        if self.num_hypotheses < 1 or self.localizer.num_dbs < 1 or self.retrieval.k < 1:
            raise ValueError("num_hypotheses, num_dbs and retrieval k must be at least 1.")
        self.search.validate()
        self.sift.validate()
        needed = {"poses": ("prior_poses", "--prior poses needs --prior-poses FILE"),
                  "hloc": ("hloc_logs", "--prior hloc needs --hloc-logs FILE (hloc's <results>_logs.pkl)")}
        files = []
        if self.prior in needed:
            attr, text = needed[self.prior]
            if not getattr(self, attr):
                raise ValueError(text + ".")
            files.append(getattr(self, attr))
        if method == "pairs":
            if not self.retrieval.pairs:
                raise ValueError("Retrieval from pairs needs a pairs file (--pairs FILE).")
            files.append(self.retrieval.pairs)
        if method == "hloc":
            if not self.retrieval.descriptors:
                raise ValueError("Retrieval from hloc descriptors needs --descriptors FILE.h5.")
            files.append(self.retrieval.descriptors)
        for f in files:
            if not Path(f).is_file():
                raise ValueError(f"Input file {f} does not exist.")
        # text inputs are read in full now: a bad line is one clear error (file:line) before
        # the run, not the same failure in every query
        if method == "pairs":
            pairs_file(self.retrieval.pairs)
        if self.prior == "poses":
            poses_file(self.prior_poses)


PRIORS = tuple(PRIOR_FUNCTIONS)  # the names of the registries: the job's and the command line's choices
RETRIEVAL_METHODS = tuple(RETRIEVERS)
POINT_SELECTIONS = ("all", "inliers", "matched")


def fit_query(query: QueryRecord) -> Tuple[QueryRecord, np.ndarray]:
    """The query's image (``pipeline.images.read_image_for``: decoded in full, its size checked
    against the camera) and the query with the camera that fits it; a resized copy is noted in
    the record. Raises ImageReadError naming the file."""
    rgb, camera, note = read_image_for(query.path, query.camera)
    if note:
        logger.warning("%s: %s", query.name, note)
        query = dataclasses.replace(query, camera=camera, notes=query.notes + (note,))
    return query, rgb


def describer(reader: MapReader, localizer: Localizer, rgb: Optional[np.ndarray], cache: Dict):
    """The query's global descriptor, computed when first asked (the network at the coarsest
    image scale, kept in ``cache`` for the refinement)."""
    def describe() -> np.ndarray:
        k_last = len(reader.conf.image_scales) - 1
        if k_last not in cache:
            cache[k_last] = localizer.predict(rgb, k_last)
        return global_descriptor(cache[k_last][0]["features"][-1][0], reader.conf.descriptor).cpu().numpy()
    return describe


def prepare_query(job: LocalizationJob, reader: MapReader, localizer: Localizer, query: QueryRecord) -> Prepared:
    """Retrieval and prior of one query (``pipeline.localization.retrieval`` and ``priors``): a
    failure (QueryResult), or its candidates."""
    if query.error:
        return failure(query, query.error)
    reason = query.camera.check()
    if reason:
        return failure(query, reason)
    try:
        query, rgb = fit_query(query)
    except ImageReadError as e:
        return failure(query, str(e))
    cache: Dict = {}
    describe = describer(reader, localizer, rgb, cache)
    return PRIOR_FUNCTIONS[job.prior](Start(job, reader, query, rgb, cache,
                                            lambda: retrieve(job.retrieval, reader, query, describe)))


FROM_MAP_POSES = ("top1", "average", "hypotheses")  # priors whose starts are the map's own poses (and the search's)


def localize_queries(job: LocalizationJob, reader: MapReader, localizer: Localizer,
                     queries: List[QueryRecord]) -> List[QueryResult]:
    """Localize ``queries`` together: one LM batch per level and group of compatible queries.

    For ``hypotheses``, each query keeps the hypothesis whose refined pose has the highest
    verification confidence (the sharpness of the cost there, ``pipeline.localization.verify``), ties broken
    by the confidence-weighted inlier fraction. All hypotheses of a query use the same points
    and features, so this compares like with like, which the final costs (means over different
    sets of valid points) do not. ``search`` screens its hypotheses at the coarsest level first
    (``pipeline.localization.search.screen``)."""
    prepared, own = [], {}  # own: each query's seconds before the LM (image, retrieval, prior)
    for q in queries:
        t0 = time.perf_counter()
        try:
            prepared.append(prepare_query(job, reader, localizer, q))
        except (OSError, ValueError, RuntimeError) as e:  # recorded, never dropped
            logger.warning("Query %s failed: %s", q.name, e)
            prepared.append(failure(q, f"{type(e).__name__}: {e}"))
        own[q.name] = time.perf_counter() - t0
    for k, p in enumerate(prepared):  # rival starts after the query's own (search.check_rivals)
        if job.prior in FROM_MAP_POSES and isinstance(p, list) and not isinstance(p, Hypotheses):
            prepared[k] = p + rival_starts(reader, p, job.localizer.verification)
    searches = [k for k, p in enumerate(prepared) if isinstance(p, Hypotheses)]
    if searches:  # the search prior, or the sift prior's fallback where PnP failed
        t0 = time.perf_counter()
        screened = screen(localizer, reader, top1_first(localizer, [prepared[k] for k in searches], job.search),
                          job.search)
        for k, p in zip(searches, screened):
            prepared[k] = p
        share = (time.perf_counter() - t0) / max(len(queries), 1)  # the screening runs as batches
        own = {name: t + share for name, t in own.items()}
    results = []
    for p, candidates, labels, j in refine_and_pick(localizer, prepared):
        if candidates is None:
            _add_time(p, [p], own)
            results.append(p)
            continue
        best = candidates[j]
        _add_time(best, candidates, own)
        if isinstance(p, Hypotheses):  # a search: report the top-1 reference's pose when rejected
            best.prior = np.asarray(p.top1, np.float64)
            merged = f" ({p.merged} more in the same basin as one of them)" if p.merged else ""
            before = "the top-1 start was not verified; " if p.first is not None else ""
            best.notes.append(f"search: {before}{p.screened} starting poses screened at the coarsest level, "
                              f"{len(candidates)} refined{merged}; the winner started from {labels[j]}")
        results.append(best)
    return results


def _add_time(result: QueryResult, candidates: List[QueryResult], own: Dict[str, float]) -> None:
    """The query's time: before the LM (``timings['prior']``: its image, retrieval and prior, from
    ``own``), plus every refined start's (``timings['total']`` of each candidate: its reference
    features, network pass and share of the batched LM)."""
    refined = sum(c.timings.get("total", 0.0) for c in candidates)
    result.timings["prior"] = own.get(result.name, 0.0)
    result.timings["total"] = result.timings["prior"] + refined


def retrieve_queries(job: LocalizationJob, queries: List[QueryRecord], out_path) -> Dict[str, Dict]:
    """The retrieval stage of a run sharded by map region: each query's ranked references
    ({name: {"dbs": [reference names], "similarity": [...] or None}}), written to ``out_path``
    (JSON, atomically; a finished file is read back). A query that cannot be read is left out:
    its shard then fails it with the reason."""
    out_path = Path(out_path)
    if out_path.exists():
        return json.loads(out_path.read_text())
    keep_freed_memory()
    out = {}
    with torch_threads(1):
        refiner, digest = localization_model(job.model, job.device)
        reader = open_reader(job.store, job.features, digest)
        localizer = Localizer(refiner.extractor, refiner.solvers, reader, job.localizer, job.device,
                              levels=job.levels, scales=job.scales)
        for q in queries:
            try:
                if q.error or q.camera is None or q.camera.check():
                    continue
                rgb = fit_query(q)[1] if job.retrieval.method == "global" else None
                found = retrieve(job.retrieval, reader, q, describer(reader, localizer, rgb, {}))
                dbs, sim = found.dbs, found.similarity
            except (OSError, ValueError, RuntimeError, ImageReadError) as e:
                logger.warning("Retrieval of %s failed: %s", q.name, e)
                continue
            out[q.name] = {"dbs": [reader.names[i] for i in dbs],
                           "similarity": None if sim is None else [float(x) for x in sim]}
    write_atomic(out_path, json.dumps(out))
    return out


def localize_shard(job: LocalizationJob, queries: List[QueryRecord], out_path) -> List[Dict]:
    """Localize ``queries`` and write their records to ``out_path``; a finished shard is read back."""
    out_path = Path(out_path)
    if out_path.exists():
        try:
            return read_records(out_path)
        except InputError as e:  # damaged since it was written (atomically): this shard runs again
            logger.warning("%s: the shard runs again", e)
    keep_freed_memory()
    with torch_threads(1):  # one thread per task: parallelism comes from workers
        refiner, digest = localization_model(job.model, job.device)
        io = None
        try:
            reader = open_reader(job.store, job.features, digest)
            localizer = Localizer(refiner.extractor, refiner.solvers, reader, job.localizer, job.device,
                                  levels=job.levels, scales=job.scales)
        except StoreError as e:  # every query gets a record with the reason
            results = [failure(q, f"map store unusable: {e}") for q in queries]
        except ValueError as e:  # a job setting the store cannot serve (image scales)
            results = [failure(q, f"job does not fit the map store: {e}") for q in queries]
        else:
            before = dict(reader.stats)
            results = localize_queries(job, reader, localizer, queries)
            io = {k: reader.stats[k] - before[k] for k in before}
    records = [result_to_record(r, q.tags) for r, q in zip(results, queries)]
    if io is not None:  # the shard's reads of the map store (shared by its queries)
        for rec in records:
            rec["store_io"] = {"shard_queries": len(queries), "bytes_read": io["bytes"],
                               "blocks_read": io["blocks"], "cache_hits": io["hits"]}
    write_records(records, out_path)
    return records
