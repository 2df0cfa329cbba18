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
from typing import ClassVar, Dict, List, Optional, Tuple

import numpy as np

from pipeline.mapping.features import FeatureConfig
from pipeline.images import ImageReadError
from pipeline.localization.refine import Localizer, LocalizerConfig, QueryCache, QueryResult
from pipeline.store.reader import MapReader, open_reader
from pipeline.models import localization_model
from pipeline.localization.priors import PRIORS, PriorSettings, Prepared, Sift, Start, Top1, failure
from pipeline.queries import QueryRecord
from pipeline.localization.results import read_records, result_to_record, write_records
from pipeline.localization.retrieval import RETRIEVERS, GlobalDescriptors, RetrievalSettings, retrieve
from pipeline.localization.query_image import describer, fit_query, read_query  # noqa: F401 (callers import them here)
from pipeline.localization.rigs import localize_frames
from pipeline.rigs import bodies_of, read_odometry, read_rigs
from pipeline.localization.search import Hypotheses, refine_and_pick, rival_starts, screen, top1_first
from pipeline.runtime import keep_freed_memory, torch_threads
from pipeline.settings import build, dotted
from pipeline.store.layout import StoreError
from pipeline.textfiles import InputError, write_atomic

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class LocalizationJob:
    """All a worker needs to localize a shard (picklable, recorded with the outputs as ``to_dict``).

    retrieval: a retrieval method's settings (an entry of ``RETRIEVERS``: how the references are
    found, ``pipeline.localization.retrieval``); prior: a prior's settings (an entry of ``PRIORS``:
    where each refinement starts, ``pipeline.localization.priors``). levels: optimise only these
    levels (the paper's refinement mode uses the two finest, (0, 1)); default all. scales: run only
    these of the store's image scales (e.g. (1,) of a [4, 1] store: refinement mode runs the full
    resolution only).

    ``to_dict`` records the schema version; ``from_dict`` reads every earlier version: a setting
    added since is read at the value that the earlier version ran with (``_from_schema_2``), else at
    its default, so that a run recorded before a setting existed is the run it was.
    """

    store: str
    features: FeatureConfig
    model: str
    localizer: LocalizerConfig
    retrieval: RetrievalSettings = GlobalDescriptors()
    prior: PriorSettings = Top1()
    device: str = "cpu"
    levels: Optional[Tuple[int, ...]] = None
    scales: Optional[Tuple[int, ...]] = None
    rigs: Optional[str] = None
    rig_frames: Optional[str] = None
    odometry: Optional[str] = None
    chunk: int = 5

    SCHEMA: ClassVar[int] = 3

    def to_dict(self) -> Dict:
        """The job as recorded in job.json (and compared by reruns, after ``from_dict``); the rig files only
        where given (a job without rigs is recorded as before them)."""
        d = asdict(self)
        d.update(schema=self.SCHEMA, retrieval=RETRIEVERS.record(self.retrieval), prior=PRIORS.record(self.prior))
        for key in ("rigs", "rig_frames", "odometry"):
            if d[key] is None:
                del d[key]
        if self.odometry is None:
            del d["chunk"]
        return d

    @classmethod
    def from_dict(cls, d: Dict, where: str = "job") -> "LocalizationJob":
        """The job that ``to_dict`` recorded, of this or an earlier schema (ValueError naming the
        key where it holds something no job has)."""
        d = json.loads(json.dumps(d))  # a deep copy: the recorded dict is not changed
        schema = d.pop("schema", 1)
        if schema == 1:
            d = _from_schema_1(d)
        if schema <= 2:
            d = _from_schema_2(d)
        retrieval = RETRIEVERS.parse(d.pop("retrieval", {"method": GlobalDescriptors.name}), where)
        prior = PRIORS.parse(d.pop("prior", {"name": Top1.name}), where)
        features = FeatureConfig.from_dict(d.pop("features", {}))
        return build(cls, dotted(d), {"features": features, "retrieval": retrieval, "prior": prior}, where=where)

    def validate(self) -> None:
        """Refuse a job that cannot run, before any query does: settings out of range, missing or
        unreadable input files."""
        if self.localizer.num_dbs < 1:
            raise ValueError("num_dbs must be at least 1.")
        self.retrieval.validate()
        self.prior.validate()
        if (self.rigs is None) != (self.rig_frames is None):
            raise ValueError("Give a rig file and a frames file together (--rigs and --rig-frames).")
        if self.rigs is not None and self.odometry is not None:
            raise ValueError("--rigs and --odometry: give one of them (a rig's frames, or a sequence's chunks).")
        if self.rigs is not None or self.odometry is not None:
            flag = "--rigs" if self.rigs is not None else "--odometry"
            if self.prior.name != Top1.name:
                raise ValueError(f"{flag}: a body starts from its images' top-1 references; --prior "
                                 f"{self.prior.name} is not there yet for rigs and sequences: use --prior {Top1.name}.")
            if self.rigs is not None:
                read_rigs(self.rigs)
            else:
                read_odometry(self.odometry, [], self.chunk, listed_only=True)


def _from_schema_1(d: Dict) -> Dict:
    """A job recorded flat (before schema 2): the prior's name in ``prior``, every prior's settings
    beside it, and the retrieval's under ``retrieval`` with every method's; each entry takes the
    keys that are its fields."""
    def own(cls, tree: Dict) -> Dict:
        return {f.name: tree[f.name] for f in dataclasses.fields(cls) if f.name in tree}
    prior = PRIORS.entry(d.pop("prior", Top1.name))
    fields = {f.name for cls in PRIORS.values() for f in dataclasses.fields(cls)}
    flat = {k: d.pop(k) for k in list(d) if k in fields}
    retrieval = dict(d.get("retrieval") or {})
    method = RETRIEVERS.entry(retrieval.pop("method", GlobalDescriptors.name))
    return {**d, "prior": {"name": prior.name, **own(prior, flat)},
            "retrieval": {"method": method.name, **own(method, retrieval)}}


def _from_schema_2(d: Dict) -> Dict:
    """A job recorded before the PnP inliers' term (schema 3): a ``sift`` job ran without it and without its
    gate (the other priors have no keypoints: the new settings change nothing there, they take the defaults)."""
    if (d.get("prior") or {}).get("name") == Sift.name:
        d.setdefault("localizer", {}).setdefault("verification", {}).setdefault("max_keypoint_chi2", 0.0)
        d["prior"].setdefault("keypoint_weight", 0.0)
    return d


def prepare_query(job: LocalizationJob, reader: MapReader, localizer: Localizer, query: QueryRecord) -> Prepared:
    """Retrieval and prior of one query (``pipeline.localization.retrieval`` and ``priors``): a
    failure (QueryResult), or its candidates."""
    query, rgb, reason = read_query(query)
    if reason:
        return failure(query, reason)
    cache = QueryCache()
    describe = describer(reader, localizer, rgb, cache)
    return job.prior.prepare(Start(reader, query, rgb, cache, lambda: retrieve(job.retrieval, reader, query, describe),
                                   job.localizer.num_dbs))


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
        if job.prior.rivals and isinstance(p, list) and not isinstance(p, Hypotheses):
            prepared[k] = p + rival_starts(reader, p, job.localizer.verification)
    searches = [k for k, p in enumerate(prepared) if isinstance(p, Hypotheses)]
    if searches:  # the search prior, or the sift prior's fallback where PnP failed
        t0 = time.perf_counter()
        conf = job.prior.search
        screened = screen(localizer, reader, top1_first(localizer, [prepared[k] for k in searches], conf), conf)
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
                rgb = fit_query(q)[1] if job.retrieval.needs_image else None
                found = retrieve(job.retrieval, reader, q, describer(reader, localizer, rgb, QueryCache()))
                dbs, sim = found.dbs, found.similarity
            except (OSError, ValueError, RuntimeError, ImageReadError) as e:
                logger.warning("Retrieval of %s failed: %s", q.name, e)
                continue
            out[q.name] = {"dbs": [reader.names[i] for i in dbs],
                           "similarity": None if sim is None else [float(x) for x in sim]}
    write_atomic(out_path, json.dumps(out))
    return out


def localize_bodies_and_queries(job: LocalizationJob, reader: MapReader, localizer: Localizer,
                                queries: List[QueryRecord]) -> List[QueryResult]:
    """The job's rig frames and chunks among ``queries`` as bodies (``pipeline.localization.rigs``; a shard holds
    whole ones, ``workflows.localize``), the other queries alone (``localize_queries``); in query order. A rig,
    frames or odometry file that cannot be read now (changed since the run was planned) fails every query of the
    shard with the reason."""
    try:
        bodies = [f for f in bodies_of(job, queries, listed_only=True) if f.tags]
    except ValueError as e:  # InputError included: the file names itself
        return [failure(q, f"rig or odometry file unusable: {e}") for q in queries]
    by_name = {r.name: r for f in localize_frames(job, reader, localizer, bodies) for r in f.images}
    alone = [q for q in queries if q.name not in by_name]
    if alone:
        by_name.update((r.name, r) for r in localize_queries(job, reader, localizer, alone))
    return [by_name[q.name] for q in queries]


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
            results = localize_bodies_and_queries(job, reader, localizer, queries)
            io = {k: reader.stats[k] - before[k] for k in before}
    records = [result_to_record(r, q.tags) for r, q in zip(results, queries)]
    if io is not None:  # the shard's reads of the map store (shared by its queries)
        for rec in records:
            rec["store_io"] = {"shard_queries": len(queries), "bytes_read": io["bytes"],
                               "blocks_read": io["blocks"], "cache_hits": io["hits"]}
    write_records(records, out_path)
    return records
