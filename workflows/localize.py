"""Batch localization workflow: shard the queries, localize shards (sync or Dask), merge.

Each shard writes ``shards/shard-XXXXX.jsonl`` atomically when done; a rerun
skips finished shards, so an interrupted run resumes without redoing or
losing work. A shard whose worker dies is retried elsewhere by Dask.
"""

import json
import logging
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List

from pipeline.queries import QueryRecord
from pipeline.results import read_records, write_poses, write_records
from pipeline.shard import LocalizationJob, localize_shard

logger = logging.getLogger(__name__)


@dataclass
class LocalizationPlan:
    job: LocalizationJob
    shards: List[List[QueryRecord]]
    output: Path

    def shard_path(self, k: int) -> Path:
        return self.output / "shards" / f"shard-{k:05d}.jsonl"

    def pending(self) -> List[int]:
        return [k for k in range(len(self.shards)) if not self.shard_path(k).exists()]

    def describe(self) -> str:
        n = sum(len(s) for s in self.shards)
        return (f"localize {n} queries in {len(self.shards)} shards ({len(self.pending())} to run) "
                f"against {self.job.store}\n  output  {self.output}\n  job     {self.job.to_dict()}")


def plan_localization(job: LocalizationJob, queries: List[QueryRecord], output, shard_size: int = 8
                      ) -> LocalizationPlan:
    if not queries:
        raise ValueError("The query list is empty: nothing to localize.")
    names = [q.name for q in queries]
    if len(set(names)) != len(names):
        raise ValueError("Query names must be unique.")
    output = Path(output)
    (output / "shards").mkdir(parents=True, exist_ok=True)
    config = output / "job.json"
    stored = json.loads(config.read_text()) if config.exists() else None
    current = {"job": job.to_dict(), "queries": names, "shard_size": shard_size}
    if stored is not None and stored != json.loads(json.dumps(current)):
        raise ValueError(f"{output} holds a run with another job or query list; use another output folder.")
    config.write_text(json.dumps(current, indent=1))
    shards = [queries[i:i + shard_size] for i in range(0, len(queries), shard_size)]
    return LocalizationPlan(job, shards, output)


def run_sync(plan: LocalizationPlan, progress: bool = False) -> List[Dict]:
    todo = plan.pending()
    if progress:
        from tqdm import tqdm
        todo = tqdm(todo, desc="shards", unit="shard")
    for k in todo:
        localize_shard(plan.job, plan.shards[k], plan.shard_path(k))
    return merge(plan)


def run_dask(plan: LocalizationPlan, client, progress: bool = False) -> List[Dict]:
    resources = {"GPU": 1} if plan.job.device.startswith("cuda") else None
    run = uuid.uuid4().hex[:8]  # keys unique per run: a key seen before would return its old result
    futures = [client.submit(localize_shard, plan.job, plan.shards[k], str(plan.shard_path(k)),
                             key=f"localize-shard-{k}-{run}", pure=False, retries=3, resources=resources)
               for k in plan.pending()]
    if progress and futures:
        from distributed import progress as dask_progress
        dask_progress(futures)
    client.gather(futures)
    return merge(plan)


def merge(plan: LocalizationPlan, prepend_camera=None) -> List[Dict]:
    """All shard records, in query order, written to records.jsonl and poses.txt."""
    records = []
    for k in range(len(plan.shards)):
        records += read_records(plan.shard_path(k))
    write_records(records, plan.output / "records.jsonl")
    write_poses(records, plan.output / "poses.txt", prepend_camera)
    return records

