"""Batch localization workflow: shard the queries, localize shards (sync or Dask), merge.

Planning writes nothing (``--dry-run`` shows the plan). With ``order="region"`` (what ``auto``
picks for runs of ``REGION_MIN_QUERIES`` queries or more whose references come from a pairs file
or hloc descriptors: ``resolve_order``), a retrieval stage runs first (``retrieval/part-XXXXX.json``,
resumable), then the queries are sharded by the map region of their top-1 reference
(``pipeline.regions``), so that a worker reads a bounded part of the store.

Running takes a lock on the output
folder (a second run into it is refused), records the job in ``job.json`` and runs what is
pending. Each shard writes ``shards/shard-XXXXX.jsonl`` atomically when done, so an
interrupted run resumes without redoing or losing work, and a finished run reruns as a
no-op. Queries that failed for a reason that a user can fix (an unreadable image, a bad line
of the list, a store chunk) are retried by a rerun, unless ``keep_failures``; refinements
that verification rejected are outcomes and are kept. A shard whose worker dies is retried
elsewhere by Dask.
"""

import contextlib
import dataclasses
import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional


from pipeline.localization.refine import QueryResult
from pipeline.localization.results import (
    is_retryable,
    read_records,
    result_to_record,
    write_failed,
    write_kapture,
    write_poses,
    write_records,
)
from pipeline.localization.shard import LocalizationJob, localize_shard, retrieve_queries
from pipeline import runtime
from pipeline.progress import count
from pipeline.queries import QueryRecord
from pipeline.regions import camera_centres, region_order
from pipeline.rigs import bodies_of
from pipeline.store.feature_groups import feature_key
from pipeline.store import location
from pipeline.store.check import store_fingerprint
from pipeline.store.info import camera_poses, image_names, tags_in_map
from pipeline.store.layout import StoreError
from pipeline.textfiles import InputError, read_json, write_atomic

from . import executor
from .locks import LOCK, output_lock

logger = logging.getLogger(__name__)
ORDERS = ("auto", "list", "region")
REGION_MIN_QUERIES = 64  # ``auto`` shards by region from this many queries on
RETRIEVAL_PART = 32  # queries per task of the retrieval stage
LOST = "no record: its shard file had lost it; run again to localize it"


class AnotherRun(ValueError):
    """The output folder holds a finished or partial run of another job, query list, order or map."""


@dataclass
class LocalizationPlan:
    """What a localization run will do. ``todo`` maps shard index -> the queries to (re)run: a
    whole pending shard, or the retryable failures of a finished one."""

    job: LocalizationJob
    shards: List[List[QueryRecord]]
    output: Path
    todo: Dict[int, List[QueryRecord]] = field(default_factory=dict)
    overwrite: bool = False
    shard_size: int = 8
    keep_failures: bool = False
    whole: set = field(default_factory=set)  # shards of ``todo`` that run whole (not written yet)
    pose_names: str = "full"  # names of an extra poses file for benchmarks (pipeline.localization.results.pose_name)
    order: str = "list"  # ``list`` (query order) or ``region`` (by the map region of the top-1 reference)
    queries: List[QueryRecord] = field(default_factory=list)  # in list order
    store: Dict = field(default_factory=dict)  # the store's fingerprint (``store_fingerprint``), into job.json
    thresholds: Optional[List] = None  # the run's recall thresholds, into job.json (evaluate and report read them)
    damaged: set = field(default_factory=set)  # finished shards whose file cannot be read: run again
    frames: Dict[str, List[str]] = field(default_factory=dict)  # with rigs: each query's frame (its images' names)

    def retrieval_path(self, part: int) -> Path:
        return self.output / "retrieval" / f"part-{part:05d}.json"

    def retrieval_parts(self) -> List[List[QueryRecord]]:
        return [self.queries[i:i + RETRIEVAL_PART] for i in range(0, len(self.queries), RETRIEVAL_PART)]

    def needs_retrieval(self) -> bool:
        """Region order whose retrieval stage has not finished (the shards are not known yet)."""
        return self.order == "region" and (self.overwrite or not all(
            self.retrieval_path(k).exists() for k in range(len(self.retrieval_parts()))))

    def apply_regions(self) -> None:
        """Shard the queries by region, from the finished retrieval stage; each query carries its
        references, so the shards do not retrieve again."""
        retrieved = {}
        for k in range(len(self.retrieval_parts())):
            retrieved.update(json.loads(self.retrieval_path(k).read_text()))
        names, centres = image_names(self.job.store), camera_centres(camera_poses(self.job.store))
        top1 = {n: (r["dbs"][0] if r["dbs"] else None) for n, r in retrieved.items()}
        order = region_order([q.name for q in self.queries], top1, names, centres)
        queries = [dataclasses.replace(self.queries[k], retrieved=retrieved.get(self.queries[k].name))
                   for k in order]
        self.shards = [queries[i:i + self.shard_size] for i in range(0, len(queries), self.shard_size)]

    def refresh(self) -> None:
        """Recompute what is to run from the shards on disk (run again under the lock: an
        interrupted run or a finished one may have changed them since planning)."""
        self.todo = {}
        self.whole = set(self.pending())
        for k, shard in enumerate(self.shards):
            if k not in self.whole:
                try:
                    done = {r["name"]: r for r in _shard_records(self, k, commit=False)}
                except InputError as e:  # written atomically, so damaged by something else: redo it
                    logger.warning("%s: its %d queries are run again", e, len(shard))
                    self.damaged.add(k)
                    self.whole.add(k)
            if k in self.whole:
                self.todo[k] = shard
            else:  # a query without a record (a shard file cut short) is always run again
                retry = {q.name for q in shard if q.name not in done
                         or (not self.keep_failures and is_retryable(done[q.name]))}
                retry = [q for q in shard if q.name in retry or set(self.frames.get(q.name, ())) & retry]
                if retry:
                    self.todo[k] = retry

    def shard_path(self, k: int) -> Path:
        return self.output / "shards" / f"shard-{k:05d}.jsonl"

    def retry_path(self, k: int) -> Path:
        return self.output / "shards" / f"shard-{k:05d}.retry.jsonl"

    def pending(self) -> List[int]:
        return [k for k in range(len(self.shards))
                if self.overwrite or k in self.damaged or not self.shard_path(k).exists()]

    def counts(self) -> Dict[str, int]:
        n = sum(len(s) for s in self.shards)
        retried = sum(len(v) for k, v in self.todo.items() if k not in self.whole)
        queued = sum(len(self.shards[k]) for k in self.whole) + retried
        return {"queries": n, "shards": len(self.shards), "to_run": queued, "retried": retried,
                "reused_queries": n - queued, "reused_shards": len(self.shards) - len(self.todo)}

    def describe(self) -> str:
        c = self.counts()
        order = ("list order" if self.order == "list" else
                 "grouped by map region after a retrieval stage" + (" (to run)" if self.needs_retrieval() else ""))
        return (f"localize {count(c['queries'], 'query')} in {count(c['shards'], 'shard')} ({order}) against "
                f"{self.job.store}\n"
                f"  to run  {count(c['to_run'], 'query')} ({count(c['retried'], 'failure')} retried); reused "
                f"{count(c['reused_queries'], 'query')}, {count(c['reused_shards'], 'finished shard')}\n"
                f"  output  {self.output}\n  model   {self.job.model}\n  prior   {self.job.prior.name}"
                + (f" from {self.job.retrieval.name} retrieval (k={self.job.retrieval.k})" if self.job.prior.retrieves
                   else ""))


OURS = {"job.json", LOCK, "shards", "retrieval", "pixloc.log"}  # what a run writes before its first shard is done


def stored_job(output: Path, overwrite: bool = False) -> Optional[Dict]:
    """The job recorded in ``output`` (None if there is none). A folder that holds files but no
    job of ours is refused: its poses.txt or records.jsonl are someone else's. A damaged job.json
    is refused with its file and line, and ignored with ``overwrite`` (which redoes the run)."""
    path = output / "job.json"
    if not path.exists():
        foreign = sorted(p.name for p in output.iterdir() if p.name not in OURS) if output.is_dir() else []
        if foreign:
            raise ValueError(f"{output} holds files that no pixloc run wrote there ({', '.join(foreign[:4])}"
                             f"{' ...' if len(foreign) > 4 else ''}): choose an empty or new --output.")
        return None
    try:
        stored = read_json(path, "job file")
        if not (isinstance(stored.get("job"), dict) and isinstance(stored.get("queries"), list)
                and isinstance(stored.get("shard_size"), int)):
            raise InputError(f"{path}: not a pixloc job file (it needs 'job', 'queries' and 'shard_size')")
    except InputError as e:
        if overwrite:
            logger.warning("%s; --overwrite: the run is redone", e)
            return None
        raise InputError(f"{e}: use --overwrite to redo the run, or another --output") from None
    return stored


def auto_shard_size(num_queries: int, workers: int) -> int:
    """Queries per task: few enough that every worker gets several tasks (no worker idles while
    another finishes a large last shard, and progress moves), at most 8 (one LM batch of 8
    amortises the per-task overhead)."""
    return max(1, min(8, -(-num_queries // (4 * max(workers, 1)))))


def resolve_order(order: str, job: LocalizationJob, num_queries: int) -> str:
    """``list`` or ``region`` for ``order``. ``auto``: region from ``REGION_MIN_QUERIES`` queries when
    the references come from a pairs file or hloc descriptors (the retrieval stage reads them, nearly
    free); list order with the store's global descriptors, whose retrieval stage would run the
    network once more per query (``--order region`` pays that to read a bounded part of the store)."""
    if order not in ORDERS:
        raise ValueError(f"Unknown query order {order!r}; known: {', '.join(ORDERS)}.")
    retrieves = job.prior.retrieves
    if order == "region" and not retrieves:
        raise ValueError(f"--order region groups queries by their retrieved references; prior {job.prior.name!r} "
                         "retrieves none.")
    bodies = job.rigs is not None or job.odometry is not None
    if order == "region" and bodies:
        raise ValueError("--order region shards queries one by one; the images of a rig frame or a chunk are "
                         "localized together: use --order list with --rigs or --odometry.")
    if order == "auto":  # a retrieval stage that runs the network costs one more network pass per query
        cheap = not job.retrieval.needs_image
        region = retrieves and cheap and num_queries >= REGION_MIN_QUERIES and not bodies
        return "region" if region else "list"
    return order


def check_same_tag(job: LocalizationJob, queries: List[QueryRecord]) -> None:
    """``--same-tag`` names a tag family that the map's images and the queries carry: one that no map
    image or no query has would restrict nothing (or everything) while job.json and the report claim
    the restriction, and is refused; queries without it (they retrieve among the map images without
    it) are said."""
    family = job.retrieval.same_tag
    if not family:
        return
    in_map = tags_in_map(job.store)
    without = [q.name for q in queries if family not in q.tags]
    if family not in in_map or len(without) == len(queries):
        where = (f"no map image has it (their tags: {', '.join(sorted(in_map)) or 'none'})" if family not in in_map
                 else f"none of the {len(queries)} queries has it")
        raise ValueError(f"--same-tag {family}: {where}; leave it out, or name a tag that the queries and the map "
                         "images carry.")
    if without:
        logger.warning("--same-tag %s: %d of the %d queries do not have it (%s%s): each retrieves among the map "
                       "images without it", family, len(without), len(queries), ", ".join(without[:3]),
                       " ..." if len(without) > 3 else "")


def plan_localization(job: LocalizationJob, queries: List[QueryRecord], output, shard_size: Optional[int] = None, *,
                      workers: int = 2, keep_failures: bool = False, overwrite: bool = False,
                      order: str = "auto", allow_partial_map: bool = False) -> LocalizationPlan:
    """Plan a run into ``output``; writes nothing. A folder holding another job, a run against
    another map (``pipeline.store.check.store_fingerprint``), or files of no run, is refused (the first
    two unless ``overwrite``, which redoes everything); so is a store with images not built yet,
    unless ``allow_partial_map``. Without ``shard_size``, a run of the same
    job and queries keeps its shard size, and a new one gets ``auto_shard_size``. ``order``:
    ``list``, ``region`` or ``auto`` (``resolve_order``)."""
    if not queries:
        raise ValueError("The query list is empty: nothing to localize.")
    inside = location.enclosing_store(output)
    if inside is not None:  # a rebuild (--overwrite) would erase the results; check-store would flag them
        raise ValueError(f"--output {output} is inside the map store {inside}: choose a folder outside any store.")
    names = [q.name for q in queries]
    order = resolve_order(order, job, len(queries))
    stored = stored_job(Path(output), overwrite)
    store = store_fingerprint(job.store, feature_key(job.features))
    check_same_tag(job, queries)
    if job.prior.retrieves:  # the retrieval's inputs checked against the map once here, not by every query
        job.retrieval.check(image_names(job.store))
    if store["pending"] is None:
        raise StoreError(f"{job.store} has no features for this configuration ({feature_key(job.features)}): "
                         "build them with pixloc build-map and the same feature settings.")
    if store["pending"] and not allow_partial_map:
        raise StoreError(f"{job.store}: {store['pending']} map images are not built yet (a build is running or was "
                         "interrupted): finish it with the same build-map command, or pass --allow-partial-map to "
                         "localize against the images done so far.")
    if stored is not None and not overwrite and "store" in stored and stored["store"]["digest"] != store["digest"]:
        raise AnotherRun(f"{output} holds results against another map (the store {job.store} was rebuilt or "
                         "changed since): use another --output, or --overwrite to redo the run against this map.")
    if stored is not None:
        stored = _current(stored)
    if shard_size is None:
        same = stored is not None and not overwrite and stored.get("queries") == names \
            and stored.get("job") == _job_json(job, names, 1, order)["job"] and stored.get("order", "list") == order
        shard_size = stored["shard_size"] if same else auto_shard_size(len(queries), workers)
    if shard_size < 1:
        raise ValueError(f"--shard-size must be at least 1, got {shard_size}.")
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"Query names must be unique; repeated: {dup[:5]}.")
    job.validate()
    output = Path(output)
    now = _job_json(job, names, shard_size, order)
    if stored is not None and not overwrite and {k: v for k, v in stored.items() if k not in RECORDED} != now:
        raise AnotherRun(f"{output} holds a run with another job, query list or order ({_changes(stored, now)}): "
                         "use another --output, or --overwrite to redo it.")
    frames = frame_groups(job, queries)
    shards = shard_frames(frames, shard_size) if frames else \
        [queries[i:i + shard_size] for i in range(0, len(queries), shard_size)]
    plan = LocalizationPlan(job, shards, output, overwrite=overwrite, shard_size=shard_size,
                            keep_failures=keep_failures, order=order, queries=list(queries), store=store,
                            frames={q.name: [p.name for p in f] for f in frames for q in f})
    if not plan.needs_retrieval():
        if order == "region":
            plan.apply_regions()
        plan.refresh()
    else:  # every shard is to run, once the retrieval stage has placed its queries
        plan.whole = set(range(len(shards)))
        plan.todo = dict(enumerate(shards))
    return plan


def frame_groups(job: LocalizationJob, queries: List[QueryRecord]) -> List[List[QueryRecord]]:
    """With rigs or a sequence: the queries of each rig frame or chunk (``pipeline.rigs.bodies_of``: the files
    read whole, a bad line an InputError naming it), a query of none alone; else none."""
    return [list(f.queries) for f in bodies_of(job, queries)]


def shard_frames(frames: List[List[QueryRecord]], shard_size: int) -> List[List[QueryRecord]]:
    """Shards of at least ``shard_size`` queries (the last may hold fewer) that never split a frame."""
    shards, current = [], []
    for f in frames:
        current += f
        if len(current) >= shard_size:
            shards.append(current)
            current = []
    return shards + ([current] if current else [])


RECORDED = ("store", "thresholds", "runtime")  # recorded in job.json, not part of the job a rerun must match


def _current(stored: Dict) -> Dict:
    """A recorded run with its job as this version records it (``LocalizationJob.from_dict``: an
    earlier schema, settings added since at their defaults), so that a rerun of the same job is
    the same run; a job no version wrote stays as it is (and differs)."""
    try:
        return {**stored, "job": json.loads(json.dumps(LocalizationJob.from_dict(stored["job"]).to_dict()))}
    except (ValueError, TypeError, KeyError):
        return stored


def _changes(stored: Dict, now: Dict, most: int = 4) -> str:
    """What differs between a run's job.json and this run's, setting by setting ('localizer.num_iters:
    40 now, 50 there'; a block that one side alone records, as a search run's search settings, once),
    then the query lists by count."""
    def said(d: Dict, k: str) -> str:
        return "not set" if k not in d else "set" if isinstance(d[k], dict) else json.dumps(d[k])

    def diff(old: Dict, new: Dict, prefix: str = "") -> List[str]:
        out = []
        for k in sorted(set(old) | set(new)):
            if isinstance(old.get(k), dict) and isinstance(new.get(k), dict):
                out += diff(old[k], new[k], f"{prefix}{k}.")
            elif old.get(k, KeyError) != new.get(k, KeyError):
                out.append(f"{prefix}{k}: {said(new, k)} now, {said(old, k)} there".removeprefix("job."))
        return out
    words = diff(*({k: v for k, v in d.items() if k not in RECORDED and k != "queries"} for d in (stored, now)))
    theirs, mine = stored.get("queries") or [], now["queries"]
    if theirs != mine:
        a, b = set(map(str, theirs)), set(map(str, mine))  # a hand-edited job.json may hold anything there
        words.append(f"queries: {len(b - a)} new, {len(a - b)} left out" if a != b else
                     "queries: the same, in another order")
    return "; ".join(words[:most]) + (f"; and {len(words) - most} more" if len(words) > most else "")


def _job_json(job: LocalizationJob, names: List[str], shard_size: int, order: str = "list",
              store: Optional[Dict] = None, thresholds=None) -> Dict:
    out = {"job": job.to_dict(), "queries": names, "shard_size": shard_size}
    if order != "list":
        out["order"] = order
    if store:
        out["store"] = {k: v for k, v in store.items() if k != "pending"}
    if thresholds:
        out["thresholds"] = [list(t) for t in thresholds]
    if store:  # the run's settings that are not the job's (``pipeline.runtime``; storage options may hold secrets)
        out["runtime"] = {"max_image_pixels": runtime.current().max_image_pixels}
    return json.loads(json.dumps(out))


def _start(plan: LocalizationPlan, run_calls) -> None:
    """Under the lock: clear an overwritten run, record the job, run the retrieval stage of a
    region-ordered run (``run_calls(fn, calls, name)`` runs tasks), and shard by region."""
    names = [q.name for q in plan.queries] or [q.name for s in plan.shards for q in s]
    if plan.overwrite:
        for folder in ("shards", "retrieval"):
            if (plan.output / folder).exists():
                shutil.rmtree(plan.output / folder)
    plan.overwrite = False  # done once: from here on the run resumes like any other
    (plan.output / "shards").mkdir(parents=True, exist_ok=True)
    write_atomic(plan.output / "job.json", json.dumps(_job_json(plan.job, names, plan.shard_size, plan.order,
                                                                plan.store, plan.thresholds),
                                                     indent=1))
    if plan.order == "region":
        parts = plan.retrieval_parts()
        todo = [k for k in range(len(parts)) if not plan.retrieval_path(k).exists()]
        if todo:
            (plan.output / "retrieval").mkdir(exist_ok=True)
            logger.info("Retrieval stage: %d queries in %d tasks, before sharding by map region.",
                        sum(len(parts[k]) for k in todo), len(todo))
            run_calls(retrieve_queries, [(plan.job, parts[k], str(plan.retrieval_path(k))) for k in todo],
                      "retrieve")
        plan.apply_regions()
    plan.refresh()


def _calls(plan: LocalizationPlan):
    return [(plan.job, queries, str(plan.shard_path(k) if k in plan.whole else plan.retry_path(k)))
            for k, queries in sorted(plan.todo.items())]


def _progress(plan: LocalizationPlan, progress: bool):
    if not progress or not plan.todo:
        return contextlib.nullcontext(None)
    from pipeline.progress import Progress
    return Progress(plan.counts()["to_run"], "localize", "query", "queries")


def run_sync(plan: LocalizationPlan, progress: bool = False) -> List[Dict]:
    """Run the plan in this process; returns every query's record, in query order."""
    with output_lock(plan.output):
        _start(plan, lambda fn, calls, name: executor.run_sync(fn, calls))
        with _progress(plan, progress) as bar:
            executor.run_sync(localize_shard, _calls(plan), on_done=(lambda r: bar.update(len(r))) if bar else None)
        return merge(plan)


def run_dask(plan: LocalizationPlan, client, progress: bool = False) -> List[Dict]:
    """Run the plan's shards as tasks of ``client``'s cluster; returns every query's record."""
    with output_lock(plan.output):
        _start(plan, lambda fn, calls, name: executor.run_dask(client, fn, calls, name, plan.job.device))
        with _progress(plan, progress) as bar:
            executor.run_dask(client, localize_shard, _calls(plan), "localize-shard", plan.job.device,
                              on_done=(lambda r: bar.update(len(r))) if bar else None)
        return merge(plan)


def _shard_records(plan: LocalizationPlan, k: int, commit: bool = True) -> List[Dict]:
    """Shard k's records, with those of a finished retry in place of the ones it redid; ``commit``
    writes them back into the shard (atomically) and removes the retry file."""
    records = read_records(plan.shard_path(k)) if plan.shard_path(k).exists() else []
    retry = plan.retry_path(k)
    if retry.exists():
        redone = {r["name"]: r for r in read_records(retry)}
        kept = {r["name"]: r for r in records}
        # in the shard's query order: a query the shard file had lost comes back from the retry
        records = [redone.get(q.name) or kept[q.name] for q in plan.shards[k] if q.name in redone or q.name in kept]
        if commit:
            write_records(records, plan.shard_path(k))
            retry.unlink()
    return records


def merge(plan: LocalizationPlan) -> List[Dict]:
    """All shard records, in query (list) order, written to records.jsonl, poses.txt (full names; and
    ``poses_{names}.txt`` with the plan's ``pose_names`` for a benchmark), kapture/ and failed.txt; with rigs,
    bodies.txt: each rig frame's rig_from_world (``key qw qx qy qz tx ty tz``)."""
    records = []
    for k in range(len(plan.shards)):
        records += _shard_records(plan, k)
    # exactly one record per query of the list, checked before the run says it is done
    have = {r["name"] for r in records}
    lost = [q for s in plan.shards for q in s if q.name not in have]
    for q in lost:
        records.append(result_to_record(QueryResult(q.name, False, None, None, [], reason=LOST), q.tags))
    if lost:
        logger.error("%d queries have no record (%s): listed as failed; rerun to localize them", len(lost),
                     ", ".join(q.name for q in lost[:3]))
    if plan.queries:  # region order: back to the order of the query list
        rank = {q.name: i for i, q in enumerate(plan.queries)}
        records.sort(key=lambda r: rank.get(r["name"], len(rank)))
    write_records(records, plan.output / "records.jsonl")
    write_poses(records, plan.output / "poses.txt")
    if plan.pose_names != "full":
        try:
            write_poses(records, plan.output / f"poses_{plan.pose_names}.txt", plan.pose_names)
        except ValueError as e:  # checked before running (cli); a library caller still gets poses.txt
            logger.error("poses_%s.txt not written: %s", plan.pose_names, e)
    bodies = {}
    for r in records:  # each rig frame's pose (rig_from_world: refined where verified, else its start)
        if r.get("body", {}).get("pose") is not None:
            bodies.setdefault(r["body"]["key"], r["body"])
    if bodies:
        write_poses([{"name": k, "success": b["success"], "refined": b["pose"], "prior": b["pose"]}
                     for k, b in bodies.items()], plan.output / "bodies.txt")
    cameras = {q.name: q.camera for s in plan.shards for q in s}
    write_kapture([r for r in records if cameras.get(r["name"]) is not None], cameras, plan.output / "kapture")
    write_failed(records, plan.output / "failed.txt")
    return records
