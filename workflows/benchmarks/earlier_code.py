"""The CPU query benchmark's queries run by an earlier commit of this project (``pixloc benchmark
query-cpu --earlier-code REV``): the real baseline of a speed-up, where the ``today`` variant only
emulates it (today's network and memory settings in today's code).

The commit's files are written into the work folder (``git archive``) and it runs in a process of its own
(``PYTHONPATH`` on the checkout, the same Python environment), on a copy of the benchmark's maps (so
that it can neither rebuild nor touch them), with its own defaults: its network as it loaded it, its
localizer and verification, one torch thread, glibc's default memory settings. Its script below uses
that commit's API: the benchmark's maps (``scene_parts``, ``sacre_coeur``), ``MapReader``,
``Localizer`` and ``localize_queries``, as they were on 2026-12-04 (commit 8975496, issue 31's filing).
Its network runs as loaded, as the workers of that commit ran it; later commits prepare it in the worker
(``pipeline.models``), which this script does not do: for them it is not their worker's query (the code of
e90cc8e ran at 1.77 CPU s here, against 1.3-1.6 s as its workers run it).
"""

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from pipeline.runtime import subprocess_environment
from pixloc.geometry import Pose, pose_error

SCRIPT = r'''
import argparse, json, sys, time
from pathlib import Path
import numpy as np
from pipeline.localization.refine import Localizer, LocalizerConfig
from pipeline.localization.retrieval import RetrievalConfig
from pipeline.localization.shard import LocalizationJob, localize_queries
from pipeline.mapping.features import FeatureConfig
from pipeline.runtime import torch_threads
from pipeline.store.reader import MapReader
from pixloc.nets.registry import DEFAULT_MODEL, load_refiner
from workflows.cli_localize import store_feature_config
from workflows.benchmarks import accuracy
from workflows.benchmarks.sacre_coeur import sacre_coeur
shared, work, out, scenes = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4].split(",")
args = argparse.Namespace(shared=shared, work=work, limit=int(sys.argv[5]))
features = FeatureConfig(model=DEFAULT_MODEL, resize=1024, image_scales=(4, 1))
parts = []
for key in scenes:
    found = accuracy.scene_parts(key, args, features) if key != "sacre_coeur" else sacre_coeur(shared, work, features)
    parts += [(n, s, q[:args.limit or None]) for n, s, q in found]
refiner = load_refiner(DEFAULT_MODEL).eval()
conf = LocalizerConfig(num_dbs=5, average_observations=True, num_iters=100)
def run():
    cpu, poses = 0.0, {}
    for name, store, queries in parts:
        reader = MapReader(store, store_feature_config(store), refiner.feature_digest())
        job = LocalizationJob(str(store), reader.conf, DEFAULT_MODEL, conf, RetrievalConfig(k=5), prior="top1")
        localizer = Localizer(refiner.extractor, refiner.solvers, reader, conf)
        with torch_threads(1):
            t0 = time.process_time()
            results = localize_queries(job, reader, localizer, queries)
            cpu += time.process_time() - t0
        for r in results:
            poses[name + "/" + r.name] = {"success": bool(r.success),
                                          "refined": None if r.refined is None else np.asarray(r.refined).tolist()}
    return cpu, poses
run()  # untimed: the images and store blocks are read once, as the benchmark's own warm-up
cpu, poses = run()
out.write_text(json.dumps({"cpu_s": cpu, "poses": poses}))
'''


def checkout(rev: str, work: Path) -> Path:
    """The files of ``rev`` (``git archive`` of this repository: nothing is registered in it) in
    ``work``, written once."""
    tree = work / f"code-{rev}"
    if not (tree / "pipeline").is_dir():
        repo = Path(__file__).resolve().parents[2]
        shutil.rmtree(tree, ignore_errors=True)
        tree.mkdir(parents=True)
        archive = subprocess.run(["git", "-C", str(repo), "archive", "--format=tar", rev], capture_output=True)
        if archive.returncode != 0:
            raise RuntimeError(f"git archive {rev}: {archive.stderr.decode(errors='replace').strip()}")
        subprocess.run(["tar", "-x", "-C", str(tree)], input=archive.stdout, check=True)
    return tree


def run_earlier(rev: str, work: Path, shared: Path, scenes: List[str], limit: int) -> Dict:
    """CPU seconds over the queries and their poses ({part/query: {success, refined}}) from ``rev``."""
    tree = checkout(rev, work)
    maps = tree / "maps"
    maps.mkdir(exist_ok=True)
    for entry in work.iterdir():  # the benchmark's maps, copied once
        if entry.suffix in (".zarr", ".work") and not (maps / entry.name).exists():
            shutil.copytree(entry, maps / entry.name)
    out = work / f"code-{rev}.json"
    env = subprocess_environment(PYTHONPATH=str(tree))
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(Path(shared).resolve()), str(maps), str(out.resolve()),
                           ",".join(scenes), str(limit)], cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"the code of {rev} failed on the benchmark's queries:\n{done.stderr[-3000:]}")
    return json.loads(out.read_text())


def pose_differences(theirs: Dict[str, Optional[np.ndarray]], ours: Dict[str, Optional[np.ndarray]],
                     metric: Dict[str, bool], scale: Dict[str, float]) -> Dict:
    """Largest differences between two runs' refined poses ({query key: 3 x 4 or None}, the same keys),
    in mm where the query's scene is metric (``metric`` per key), else in % of its ``scale``; and the
    queries refined by one run and not the other."""
    dt_mm, dt_pct, dR, unmatched = [0.0], [0.0], [0.0], 0
    for key, mine in ours.items():
        other = theirs.get(key)
        if (other is None) != (mine is None):
            unmatched += 1
            continue
        if mine is None:
            continue
        R, t = pose_error(*(Pose.from_matrix(np.asarray(x, np.float64)) for x in (other, mine)))
        (dt_mm if metric[key] else dt_pct).append(1000 * float(t) if metric[key] else 100 * float(t) / scale[key])
        dR.append(float(R))
    return {"max_dt_mm": max(dt_mm), "max_dt_pct": max(dt_pct), "max_dR": max(dR), "unmatched": unmatched}
