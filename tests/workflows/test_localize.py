"""Batch localization end to end on real data: outputs, evaluation, Dask, failures, resume."""

import dataclasses
import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.mapping.build import build_map
from pipeline.mapping.depth import rgbd_scene
from pipeline.evaluate import INDOOR_THRESHOLDS, evaluate, pose_errors
from pipeline.mapping.features import FeatureConfig
from pipeline.localization.refine import LocalizerConfig
from pipeline.mapping.readers.rgbd import read_7scenes
from pipeline.localization.results import read_records, record_pose
from pipeline.localization.priors import Hloc, OtherPipeline
from pipeline.localization.retrieval import GlobalDescriptors, PairsFile, HlocDescriptors
from pipeline.localization.shard import LocalizationJob
from tests.workflows.test_build_map import KINECT_K, build_kinect, cluster  # noqa: F401  (fixture)
from workflows.process_cluster import wait_for
from workflows.localize import plan_localization, run_dask, run_sync
from pipeline.mapping.readers.sources import load_queries

ROOT = Path(__file__).resolve().parents[2]
FCONF = FeatureConfig(resize=320, image_scales=(1,))
LCONF = LocalizerConfig(num_dbs=3, num_iters=15)


def without_timings(records):
    """Records less what depends on the run, not on the query: timings, and the store reads of
    the shard (which depend on what the worker's block cache already held)."""
    return [{k: v for k, v in r.items() if k not in ("timings", "store_io")} for r in records]


@pytest.fixture(scope="module")
def seven_scenes(shared, tmp_path_factory):
    """An RGB-D map of 7-Scenes stairs sequences 2 and 3, and the queries of sequences 1 and 4."""
    root = shared / "data" / "7scenes_stairs"
    store = tmp_path_factory.mktemp("map") / "map.zarr"
    scene = rgbd_scene(read_7scenes(root, [2, 3]), method="frames", stride=24)
    build_map(scene, store, FCONF)
    queries = load_queries("7scenes", root, sequences=(1, 4))
    job = LocalizationJob(str(store), FCONF, FCONF.model, LCONF, GlobalDescriptors(k=5))
    return job, queries


@pytest.fixture(scope="module")
def sync_records(seven_scenes, tmp_path_factory):
    job, queries = seven_scenes
    return run_sync(plan_localization(job, queries, tmp_path_factory.mktemp("sync"), shard_size=2))


def test_7scenes_with_retrieval(seven_scenes, sync_records):
    job, queries = seven_scenes
    assert [r["name"] for r in sync_records] == [q.name for q in queries]  # one record each, in order
    gt = {q.name: q.cam_from_world_gt for q in queries}
    for r in sync_records:
        assert r["references"] and all(ref.startswith(("seq-02/", "seq-03/")) for ref in r["references"])
        assert r["tags"]["sequence"] in ("seq-01", "seq-04")
        assert len(r["per_level"]) == 3 and r["num_points"] >= 10 and 0 <= r["confidence"] <= 1
        # The retrieved priors are ~46 deg off, out of reach of a local refinement: verification must not
        # report a refinement that ends wrong (> 1 m or > 5 deg) as a success.
        t, R = pose_errors(np.asarray(r["refined"]), gt[r["name"]])
        if t > 1.0 or R > 5.0:
            assert not r["success"] and r["reason"].startswith("rejected: ")
    summary = evaluate(sync_records, gt, INDOOR_THRESHOLDS)
    assert set(summary) == {"all", "sequence=seq-01", "sequence=seq-04"}
    assert summary["all"]["refined"]["count"] == 6
    # The numbers go in the closing note; the untrained network cannot be held to accuracy here.
    print(json.dumps({k: {w: v[w] for w in ("prior", "refined")} for k, v in summary.items()}, indent=1))


def test_points_per_cell_subsamples_only_the_crowded_levels(seven_scenes, sync_records, tmp_path):
    """--points-per-cell 1: the coarsest level (20 x 15 cells at 320 px) runs on a seeded subset of
    1,024 residuals; the finer levels, with more cells than points, on all of them; rerun, the same."""
    job, queries = seven_scenes
    sub = dataclasses.replace(job, localizer=dataclasses.replace(LCONF, points_per_cell=1.0))
    a = run_sync(plan_localization(sub, queries[:1], tmp_path / "a"))[0]
    b = run_sync(plan_localization(sub, queries[:1], tmp_path / "b"))[0]
    full = [lv["residuals"] for lv in sync_records[0]["per_level"]]
    assert full[0] > 1024 and [lv["residuals"] for lv in a["per_level"]] == [1024] + full[1:]
    assert a["refined"] == b["refined"] and a["per_level"] == b["per_level"]
    assert a["per_level"][0]["pose"] != sync_records[0]["per_level"][0]["pose"]  # a subset is not all


def test_outputs(seven_scenes, sync_records, tmp_path):
    job, queries = seven_scenes
    plan = plan_localization(job, queries, tmp_path, shard_size=2)
    run_sync(plan)
    lines = (tmp_path / "poses.txt").read_text().splitlines()
    assert len(lines) == 6
    name, *values = lines[0].split()
    # 7-Scenes basenames repeat across sequences: names get their folder (visuallocalization.net practice).
    assert name == queries[0].name == "seq-01/frame-000000.color.jpg" and len(values) == 7
    q = np.array(values[:4], float)
    assert abs(np.linalg.norm(q) - 1) < 1e-6 and q[0] >= 0
    assert without_timings(read_records(tmp_path / "records.jsonl")) == without_timings(sync_records)
    # benchmark names: 7-Scenes basenames repeat across sequences, so only parentdir/basename is refused nothing
    from pipeline.localization.results import pose_names_problem
    assert "makes query names alike" in pose_names_problem([q.name for q in queries], "basename")
    assert pose_names_problem([q.name for q in queries], "camera") is None
    plan.pose_names = "camera"
    run_sync(plan)  # a finished run: merges again, with the extra file
    assert (tmp_path / "poses_camera.txt").read_text() == (tmp_path / "poses.txt").read_text()  # seq-XX/frame...
    # the same poses as a kapture folder (device_from_world), read back by the kapture reader
    from pipeline.mapping.readers.kapture import read_kapture
    back = {im.name: im for im in read_kapture(tmp_path / "kapture")}
    assert sorted(back) == sorted(q.name for q in queries)
    for r in sync_records:
        assert np.allclose(back[r["name"]].cam_from_world, record_pose(r), atol=1e-4)  # priors: float32 rotations
        assert back[r["name"]].camera == next(q.camera for q in queries if q.name == r["name"])


def test_distributed_equals_sync_and_survives_a_killed_worker(seven_scenes, sync_records, cluster, tmp_path):  # noqa: F811
    client, workers = cluster
    job, queries = seven_scenes
    records = run_dask(plan_localization(job, queries, tmp_path / "a", shard_size=2), client)  # as sync_records
    assert without_timings(records) == without_timings(sync_records)
    plan = plan_localization(job, queries, tmp_path / "b", shard_size=1)
    outcome = {}
    runner = threading.Thread(target=lambda: outcome.update(records=run_dask(plan, client)))
    runner.start()
    wait_for(lambda: len(list((tmp_path / "b" / "shards").glob("*.jsonl"))) >= 1)
    workers["a"].send_signal(signal.SIGKILL)
    runner.join(600)
    names = [r["name"] for r in outcome["records"]]
    assert names == [q.name for q in queries]  # every query exactly once


def test_bad_input_gives_per_query_failures(seven_scenes, tmp_path):
    job, queries = seven_scenes
    corrupt = tmp_path / "corrupt.jpg"
    corrupt.write_bytes(b"\xff\xd8 not really")
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{queries[3].name} not/in/the/map.jpg\n")
    bad = [dataclasses.replace(queries[0], path=tmp_path / "missing.jpg"),
           dataclasses.replace(queries[1], path=corrupt), queries[2]]
    records = run_sync(plan_localization(job, bad, tmp_path / "a"))
    assert [r["success"] for r in records][:2] == [False, False] and records[2]["per_level"]
    assert "missing" in records[0]["reason"] and "cannot be decoded" in records[1]["reason"]
    # no retrieval match
    pjob = dataclasses.replace(job, retrieval=PairsFile(pairs=str(pairs)))
    rec = run_sync(plan_localization(pjob, [queries[3]], tmp_path / "b"))[0]
    assert not rec["success"] and "no retrieval match" in rec["reason"]
    # references seeing fewer than min_points points
    fjob = dataclasses.replace(job, localizer=dataclasses.replace(LCONF, min_points=10**6))
    rec = run_sync(plan_localization(fjob, [queries[3]], tmp_path / "c"))[0]
    assert not rec["success"] and "points (< 1000000)" in rec["reason"] and rec["prior"] is not None
    # ... because their points are seen by too few map images: the reason says so (a map of two images)
    tjob = dataclasses.replace(job, localizer=dataclasses.replace(LCONF, min_track_length=10**6))
    rec = run_sync(plan_localization(tjob, [queries[3]], tmp_path / "c2"))[0]
    short = rec["filters"]["short_tracks"]
    assert short > 0 and rec["reason"] == (f"references see 0 points (< {LCONF.min_points}); {short} more are seen "
                                           "by fewer than 1000000 map images (--min-track-length)")
    # a store built with another model
    ojob = dataclasses.replace(job, model=str(ROOT / "nope.tar"))
    with pytest.raises(ValueError, match="Unknown feature model"):
        run_sync(plan_localization(ojob, [queries[3]], tmp_path / "d"))
    with pytest.raises(ValueError, match="query list is empty"):
        plan_localization(job, [], tmp_path / "e")


def test_store_of_another_model_fails_each_query(seven_scenes, official_checkpoint, tmp_path):
    job, queries = seven_scenes
    ckpt = str(official_checkpoint)
    ojob = dataclasses.replace(job, model=ckpt)
    records = run_sync(plan_localization(ojob, queries[:2], tmp_path))
    assert [r["success"] for r in records] == [False, False]
    assert all("map store unusable" in r["reason"] and "not the localizer's" in r["reason"] for r in records)


def test_interrupted_run_resumes_by_shard(seven_scenes, tmp_path):
    job, queries = seven_scenes
    plan = plan_localization(job, queries, tmp_path, shard_size=1)
    script = ("import sys, pickle; sys.path.insert(0, sys.argv[1])\n"
              "from workflows.localize import run_sync\n"
              "run_sync(pickle.load(open(sys.argv[2], 'rb')))\n")
    import pickle
    (tmp_path / "plan.pkl").write_bytes(pickle.dumps(plan))
    proc = subprocess.Popen([sys.executable, "-c", script, str(ROOT), str(tmp_path / "plan.pkl")])
    wait_for(lambda: len(plan.pending()) <= 4, timeout=300)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    finished = {k: plan.shard_path(k).stat().st_mtime_ns for k in range(6) if plan.shard_path(k).exists()}
    assert 2 <= len(finished) < 6
    time.sleep(0.01)
    records = run_sync(plan)
    assert [r["name"] for r in records] == [q.name for q in queries]
    assert all(plan.shard_path(k).stat().st_mtime_ns == t for k, t in finished.items())  # not redone


def test_html_report(seven_scenes, tmp_path):
    """The report's sections and their contents, checked in the HTML (the browser test renders the demo's)."""
    import base64
    import re

    from workflows.report import make_report
    job, queries = seven_scenes
    records = run_sync(plan_localization(job, queries, tmp_path, shard_size=3))
    path = make_report(tmp_path, queries, num_examples=2, thresholds=INDOOR_THRESHOLDS, units="m")
    page = path.read_text()
    images = re.findall(r'src="data:image/(png|jpeg);base64,([A-Za-z0-9+/=]+)"', page)
    magic = {"png": b"\x89PNG\r\n\x1a\n", "jpeg": b"\xff\xd8\xff"}
    assert all(base64.b64decode(b)[:len(magic[f])] == magic[f] for f, b in images)
    # curves of 'all' and of the 'sequence' family (two values) and the top view; no curves for 'split' (one
    # value); the verification threshold's section says that no refinement is right (the map's images are
    # 41-53 deg from every query), instead of two curves flat at zero
    assert sum(f == "png" for f, _ in images) == 3 and "id='threshold'" in page
    assert "None of the refined queries with ground truth is within 0.05 m, 5 deg" in page
    # per sequence the best and the worst query, then failures of other kinds
    assert 4 <= sum(f == "jpeg" for f, _ in images) <= 7
    assert page.count("(sequence=seq-01: best by error)") == 1 and "(sequence=seq-04: worst by error)" in page
    for section in ("id='accuracy'", "id='family-all'", "id='family-sequence'", "id='failures-section'",
                    "id='queries'", "id='map'", "id='examples'"):
        assert section in page
    assert "within 0.05 m, 5&deg;" in page and "nan" not in re.sub(r"base64,[^\"]+", "", page).lower()
    table = page[page.index("<table id='queries'"):]
    rows = re.findall(r"<tr class='(refined|rejected|failed)'><td>([^<]+)</td>", table[:table.index("</table>")])
    assert sorted(n for _, n in rows) == sorted(q.name for q in queries)
    order = [{"failed": 0, "rejected": 1, "refined": 2}[o] for o, _ in rows]
    assert order == sorted(order)  # failures first
    assert sum(o != "refined" for o, _ in rows) == sum(not r["success"] for r in records)
    # one query without ground truth: its errors are '-', the medians are over the others, never 'nan'
    from workflows.report import accuracy_tables, query_errors, query_table
    gt = {q.name: q.cam_from_world_gt for q in queries}
    gt[queries[0].name] = None
    summary = evaluate(records, gt, INDOOR_THRESHOLDS)
    errors = {r["name"]: query_errors(r, gt[r["name"]]) for r in records}
    part = accuracy_tables(summary, INDOOR_THRESHOLDS, "m") + query_table(records, errors, INDOOR_THRESHOLDS, "m")
    assert "nan" not in re.sub(r"base64,[^\"]+", "", part).lower() and "<td>all</td><td>5</td>" in part
    missing = part[part.index(f"<td>{queries[0].name}</td>"):]
    assert missing.split("</tr>")[0].count("<td data-v=''>-</td>") >= 4


def test_hloc_descriptors_and_refinement_mode(seven_scenes, sync_records, tmp_path):
    import h5py

    from pipeline.store.reader import MapReader
    job, queries = seven_scenes
    reader = MapReader(job.store, FCONF)
    # An hloc-style global-features file: the map's descriptors, and each query as a copy of
    # one reference's, so that retrieval must rank that reference first.
    wanted = {q.name: reader.names[(3 * i) % len(reader.names)] for i, q in enumerate(queries)}
    with h5py.File(tmp_path / "global.h5", "w") as f:
        for i, name in enumerate(reader.names):
            f.create_dataset(f"{name}/global_descriptor", data=reader.global_descriptors[i])
        for q, ref in wanted.items():
            f.create_dataset(f"{q}/global_descriptor", data=reader.global_descriptors[reader.index[ref]])
    hjob = dataclasses.replace(job, retrieval=HlocDescriptors(descriptors=str(tmp_path / "global.h5")))
    records = run_sync(plan_localization(hjob, queries, tmp_path / "h"))
    assert [r["references"][0] for r in records] == [wanted[q.name] for q in queries]
    # Refinement mode: start from another pipeline's poses, two finest levels only.
    (tmp_path / "poses.txt").write_text((tmp_path / "h" / "poses.txt").read_text())
    rjob = dataclasses.replace(job, prior=OtherPipeline(str(tmp_path / "poses.txt")), levels=(0, 1))
    refined = run_sync(plan_localization(rjob, queries, tmp_path / "r"))
    for r, prev in zip(refined, records):
        assert [lvl["level"] for lvl in r["per_level"]] == [1, 0]
        # 1e-4: a rejected query's line is its reference's 7-Scenes pose, whose rotation is not exactly
        # orthonormal; written as a quaternion, it comes back orthonormalised
        np.testing.assert_allclose(np.asarray(r["prior"]), np.asarray(prev["refined"] if prev["success"]
                                                                      else prev["prior"]), atol=1e-4)


def test_shard_batches_queries_like_one_at_a_time(seven_scenes, sync_records):
    """A shard solves its queries as one LM batch per level; each result equals a solo run."""
    from pipeline.localization.refine import Localizer
    from pipeline.store.reader import MapReader
    from pipeline.localization.shard import localize_queries
    from pipeline.models import localization_model
    job, queries = seven_scenes
    refiner, digest = localization_model(job.model)
    reader = MapReader(job.store, FCONF, digest)
    localizer = Localizer(refiner.extractor, refiner.solvers, reader, LCONF)
    calls = []
    original = localizer.localize_batch
    localizer.localize_batch = lambda items: calls.append(len(items)) or original(items)
    batched = localize_queries(job, reader, localizer, queries)
    assert calls == [12]  # one batch for the six 640x480 queries and their rival starts (one each)
    solo = {r["name"]: r for r in sync_records}  # shards of 2
    for r in batched:
        np.testing.assert_allclose(r.refined, np.asarray(solo[r.name]["refined"]), atol=1e-4)
        assert r.iterations == solo[r.name]["iterations"]


def test_region_order_shards_by_reference_region_and_resumes(seven_scenes, sync_records, tmp_path):
    """A retrieval stage, then shards of queries whose top-1 references are neighbours: the same
    poses as in list order, records in list order, and a rerun redoes neither stage."""
    job, queries = seven_scenes
    plan = plan_localization(job, queries, tmp_path, shard_size=2, order="region")
    assert plan.needs_retrieval() and "retrieval stage (to run)" in plan.describe()
    records = run_sync(plan)
    assert [r["name"] for r in records] == [q.name for q in queries]
    by_name = {r["name"]: r for r in sync_records}
    for r in records:
        assert r["references"] == by_name[r["name"]]["references"]
        np.testing.assert_allclose(r["refined"], by_name[r["name"]]["refined"], atol=1e-4)
        assert r["store_io"]["shard_queries"] >= 1
    # shards follow the Z-order of the top-1 reference centres: queries with the same top-1 are together
    again = plan_localization(job, queries, tmp_path, shard_size=2, order="region")
    assert not again.needs_retrieval() and not again.todo
    top1 = [q.retrieved["dbs"][0] for s in again.shards for q in s]
    assert sorted(set(top1), key=top1.index) == [k for k, _ in itertools.groupby(top1)]
    parts = sorted((tmp_path / "retrieval").glob("part-*.json"))
    stamp = [p.stat().st_mtime_ns for p in parts]
    again.shard_path(1).unlink()
    resumed = plan_localization(job, queries, tmp_path, shard_size=2, order="region")
    assert list(resumed.todo) == [1]
    run_sync(resumed)
    assert [p.stat().st_mtime_ns for p in parts] == stamp
    with pytest.raises(ValueError, match='another job, query list or order \\(order: not set now, "region" there\\)'):
        plan_localization(job, queries, tmp_path, shard_size=2, order="list")
    # the refusal names what differs: each setting, then the query lists by count
    n = job.localizer.num_iters
    other = dataclasses.replace(job, localizer=dataclasses.replace(job.localizer, num_iters=n + 1))
    with pytest.raises(ValueError, match=f"localizer.num_iters: {n + 1} now, {n} there; queries: 0 new, 1 left out"):
        plan_localization(other, queries[1:], tmp_path, shard_size=2, order="region")


def test_auto_order_groups_by_region_only_where_retrieval_is_free():
    from workflows.localize import REGION_MIN_QUERIES, resolve_order
    job = LocalizationJob("map.zarr", FCONF, FCONF.model, LCONF, GlobalDescriptors(k=5))
    pairs = dataclasses.replace(job, retrieval=PairsFile(pairs="pairs.txt", k=5))
    assert resolve_order("auto", pairs, REGION_MIN_QUERIES) == "region"
    assert resolve_order("auto", pairs, REGION_MIN_QUERIES - 1) == "list"
    assert resolve_order("auto", job, 10 ** 5) == "list"  # global descriptors: one more network pass per query
    assert resolve_order("region", job, 2) == "region"
    with pytest.raises(ValueError, match="retrieves none"):
        resolve_order("region", dataclasses.replace(job, prior=Hloc("logs.pkl")), 100)


def test_ctrl_c_or_sigterm_stops_the_run_with_one_line(shared, tmp_path):
    """Ctrl-C goes to every process of the terminal's group: the local cluster's worker processes too.
    Before, each printed a KeyboardInterrupt traceback, then a warning per cancelled task; SIGTERM gave
    glog's stack dump and no cleanup. Now the command alone stops the run and says so in one line, its
    workers end with it, and the same command resumes it."""
    kinect = shared / "data" / "rgbd_slambook" / "kinect_room"
    built = build_kinect(kinect, tmp_path / "k.zarr", "--rgbd-points", "frames")
    assert built.returncode == 0, built.stderr
    localize = [sys.executable, "-m", "workflows.cli", "localize", "posetxt", str(kinect), "--intrinsics", *KINECT_K,
                "--store", str(tmp_path / "k.zarr"), "--output", str(tmp_path / "out"), "--workers", "2"]
    for sig, code, said in ((signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated (SIGTERM)")):
        # a session of its own, as a terminal's (or a batch job's): the signal to its group reaches the
        # client and the workers
        proc = subprocess.Popen(localize, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT,
                                start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if "queries to do" in line:  # the workers are running the first tasks
                time.sleep(1.0)
                os.killpg(proc.pid, sig)
                break
        lines += proc.stdout.readlines()
        text = "".join(lines)
        assert proc.wait(timeout=120) == code, text
        assert f"pixloc: {said}; run the same command again to resume" in text
        for noise in ("Traceback", "KeyboardInterrupt", "CancelledError", "Aborted at", "SIGTERM received"):
            assert noise not in text, text  # SIGTERM: glog's failure handler printed a stack dump
        wait_for(lambda: not _group_alive(proc.pid), timeout=30)  # no worker process left behind
    done = subprocess.run(localize, capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0 and "5 queries (" in done.stdout, done.stdout + done.stderr


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
        return True
    except ProcessLookupError:
        return False


def test_covisible_retrieval_ranks_the_map_images_by_the_points_they_see_in_view(seven_scenes, tmp_path):
    """A retrieval method added as a newcomer adds one: ``covisible`` ranks the map images by the map
    points they observe inside the query's view at a prior pose (a poses file): a query's ranking
    follows the counts of points in view, and a map image given its own pose sees all the points it
    observes and retrieves images of its own sequence (the stairs' two are 50 deg apart)."""
    from pipeline.localization.retrieval import RETRIEVERS, Covisible, retrieve
    from pipeline.textfiles import poses_file
    from pipeline.mapping.readers.sources import as_query
    from pipeline.store.info import map_images
    from pipeline.store.reader import MapReader
    from workflows.benchmarks.verification import write_priors
    job, queries = seven_scenes
    assert RETRIEVERS["covisible"] is Covisible
    images = map_images(job.store)
    own = [as_query(im) for im in images]
    poses = tmp_path / "priors.txt"
    write_priors(poses, {q.name: np.asarray(q.cam_from_world_gt) for q in queries + own})
    conf = Covisible(k=len(images), poses=str(poses))
    conf.validate()
    reader = MapReader(job.store, job.features)
    def in_view(q):
        T = np.asarray(poses_file(str(poses)).find(q.name))  # as the method reads it
        cam = reader.xyz @ T[:, :3].T + T[:, 3]
        f, (cx, cy) = q.camera.focals(), q.camera.principal_point()
        u, v = f[0] * cam[:, 0] / cam[:, 2] + cx, f[-1] * cam[:, 1] / cam[:, 2] + cy
        return (cam[:, 2] > 0) & (u >= 0) & (u < q.camera.width) & (v >= 0) & (v < q.camera.height)
    for k, q in enumerate(own):
        found = retrieve(conf, reader, q, lambda: None)
        assert in_view(q)[reader.image_points(k)].mean() > 0.98
        assert [reader.names[i].split("/")[0] for i in found.dbs[:3]] == [q.name.split("/")[0]] * 3
    for q in queries:
        found, seen = retrieve(conf, reader, q, lambda: None), in_view(q)
        counts = [int(seen[reader.image_points(i)].sum()) for i in found.dbs]
        assert found.dbs and counts == sorted(counts, reverse=True) and counts[-1] > 0
        assert np.allclose(found.similarity, np.asarray(counts) / counts[0])
    records = run_sync(plan_localization(dataclasses.replace(job, retrieval=conf), queries[:2], tmp_path / "run"))
    assert all(r["references"] for r in records)
    missing = dataclasses.replace(job, retrieval=Covisible(poses=str(tmp_path / "none.txt")))
    with pytest.raises(ValueError, match="does not exist"):
        plan_localization(missing, queries, tmp_path / "none")
