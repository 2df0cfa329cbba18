"""The catalogue of bad inputs and faults, each with the outcome a user gets.

Every case runs the real pipeline on real data (a 7-Scenes RGB-D map of sequences 2 and 3,
queries of 1 and 4) and checks what comes out: a per-query failure with its reason, a clear
refusal, or a recovery. Read top to bottom, it is the list of what the tool guards against.
"""

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.mapping.build import build_map
from pipeline.mapping.depth import rgbd_scene
from pipeline.evaluate import evaluate, to_json
from pipeline.mapping.features import FeatureConfig
from pipeline.localization.refine import LocalizerConfig
from pipeline.mapping.readers.hloc import parse_loc
from pipeline.mapping.readers.rgbd import read_7scenes
from pipeline.localization.results import read_records
from pipeline.localization.priors import Hloc, OtherPipeline, ReferenceHypotheses, Search
from pipeline.localization.retrieval import GlobalDescriptors, PairsFile
from pipeline.localization.shard import LocalizationJob
from pipeline.store.feature_groups import feature_key
from pipeline.store.layout import StoreError, open_store
from pipeline.store.check import check_store
from workflows.localize import plan_localization, run_sync
from workflows.locks import OutputLocked, output_lock
from pipeline.mapping.readers.sources import load_queries

ROOT = Path(__file__).resolve().parents[3]
FCONF = FeatureConfig(resize=320, image_scales=(1,))
LCONF = LocalizerConfig(num_dbs=3, num_iters=15)


@pytest.fixture(scope="module")
def stairs(shared, tmp_path_factory):
    root = shared / "data" / "7scenes_stairs"
    store = tmp_path_factory.mktemp("faults") / "map.zarr"
    build_map(rgbd_scene(read_7scenes(root, [2, 3]), method="frames", stride=24), store, FCONF)
    queries = load_queries("7scenes", root, sequences=(1, 4))
    job = LocalizationJob(str(store), FCONF, FCONF.model, LCONF, GlobalDescriptors(k=5))
    return job, queries, root


def pixloc(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "workflows.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env={**os.environ, "PYTHONPATH": str(ROOT)})


# --- images -------------------------------------------------------------------------------

def test_truncated_query_jpeg_fails_that_query(stairs, tmp_path):
    """Before: libjpeg only printed a warning and the grey-padded image gave a 'successful' pose."""
    job, queries, _ = stairs
    data = queries[0].path.read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) // 2])
    bad = [dataclasses.replace(queries[0], path=tmp_path / "cut.jpg"), queries[1]]
    records = run_sync(plan_localization(job, bad, tmp_path / "out"))
    assert not records[0]["success"] and "cut.jpg" in records[0]["reason"]
    assert "truncated or corrupt" in records[0]["reason"] or "cannot be decoded" in records[0]["reason"]
    assert records[1]["reason"] == "" or records[1]["reason"].startswith("rejected")  # the other one ran


def test_truncated_map_image_is_recorded_as_failed_and_the_map_built(shared, tmp_path):
    import shutil

    from pipeline.mapping.readers.colmap import read_colmap
    from pipeline.store.layout import FAILED
    root = shared / "data" / "maupertuis"
    shutil.copytree(root / "images", tmp_path / "images")
    scene = read_colmap(root / "reconstruction", tmp_path / "images")
    victim = scene.images[1].path
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) * 2 // 3])
    conf = FeatureConfig(resize=256, image_scales=(1,))
    results = build_map(scene, tmp_path / "m.zarr", conf)
    assert [r.status for r in results] == ["done", "failed", "done", "done"]
    assert "truncated or corrupt" in results[1].reason or "cannot be decoded" in results[1].reason
    group = open_store(tmp_path / "m.zarr")[f"features/{feature_key(conf)}"]
    assert group["status"][1] == FAILED and victim.name in str(group["reason"][1])


# --- query lists ---------------------------------------------------------------------------

def test_malformed_query_lines_fail_their_query_with_file_and_line(stairs, tmp_path):
    """Before: one bad line aborted the whole run without a file or line number."""
    job, queries, root = stairs
    q = queries[0]
    good = f"{q.name} PINHOLE 640 480 525 525 320 240"
    (tmp_path / "list.txt").write_text(f"# queries\n{good}\nseq-01/frame-000001.color.jpg PINHOLE 640\n"
                                       "seq-01/frame-000002.color.jpg PINHOLE 640 480 525 525 320\n")
    listed = load_queries("list", tmp_path / "list.txt", root)
    assert [x.error is None for x in listed] == [True, False, False]
    records = run_sync(plan_localization(job, listed, tmp_path / "out"))
    assert records[1]["reason"].startswith(f"{tmp_path / 'list.txt'}:3: bad query line")
    assert records[2]["reason"].startswith(f"{tmp_path / 'list.txt'}:4: bad query line")
    assert "has 4 parameters, got 3" in records[2]["reason"]
    assert records[0]["references"]  # the good line ran


def test_declared_image_size_is_checked(stairs, tmp_path):
    """Same aspect ratio: intrinsics rescaled to the file (noted); another aspect ratio: failure."""
    job, queries, root = stairs
    q = queries[0]
    (tmp_path / "list.txt").write_text(f"{q.name} PINHOLE 1280 960 1050 1050 640 480\n"
                                       f"{queries[1].name} PINHOLE 640 360 525 525 320 180\n")
    records = run_sync(plan_localization(job, load_queries("list", tmp_path / "list.txt", root), tmp_path / "o"))
    assert "intrinsics rescaled" in records[0]["notes"][0] and records[0]["references"]
    assert not records[1]["success"] and "another aspect ratio" in records[1]["reason"]


# --- map store -----------------------------------------------------------------------------

def _copy_store(job, tmp_path) -> Path:
    import shutil
    path = tmp_path / "copy.zarr"
    shutil.copytree(job.store, path)
    return path


def _feature_chunk(store: Path, image: int) -> Path:
    root = open_store(store)
    shard = root.attrs["pixloc_map"]["shard_rows"]
    row = int(root["images/row_start"][image])
    return store / "features" / feature_key(FCONF) / "s0" / "features" / "c" / str(row // shard) / "0"


@pytest.mark.parametrize("damage", ["flip", "truncate"])
def test_damaged_chunk_fails_the_queries_that_need_it(stairs, tmp_path, damage):
    """Before: a flipped byte decoded silently to garbage; a truncated chunk gave a 225-line traceback."""
    job, queries, _ = stairs
    store = _copy_store(job, tmp_path)
    first = run_sync(plan_localization(dataclasses.replace(job, store=str(store)), queries[:1], tmp_path / "a"))
    ref = first[0]["references"][0]
    index = [str(n) for n in open_store(store)["images/name"][:]].index(ref)
    chunk = _feature_chunk(store, index)
    data = bytearray(chunk.read_bytes())
    if damage == "flip":
        data[len(data) // 2] ^= 0x10
    else:
        data = data[: len(data) // 2]
    chunk.write_bytes(bytes(data))
    from pipeline.store import reader as map_reader
    map_reader.forget_readers()  # the damage happens between runs: a new process would not have read the block
    records = run_sync(plan_localization(dataclasses.replace(job, store=str(store)), queries[:1], tmp_path / "b"))
    assert not records[0]["success"]
    assert "s0/features" in records[0]["reason"] and ref in records[0]["reason"]
    report = check_store(store)
    assert not report.ok and len(report.bad) == 1 and ref in report.bad[0].images
    out = pixloc("check-store", store)
    assert out.returncode == 1 and "bad chunk" in out.stdout and ref in out.stdout
    assert pixloc("check-store", job.store).returncode == 0


def test_missing_array_metadata_is_refused_at_open(stairs, tmp_path):
    """Before: a KeyError after 642 s of work."""
    job, _, _ = stairs
    store = _copy_store(job, tmp_path)
    (store / "observations" / "point" / "zarr.json").unlink()
    with pytest.raises(StoreError, match="observations/point is missing"):
        open_store(store)


def test_contradicting_attributes_are_refused_at_open(stairs, tmp_path):
    """Before: absurd sizes led to a 1.46 TiB allocation."""
    job, _, _ = stairs
    store = _copy_store(job, tmp_path)
    meta_path = store / "zarr.json"
    meta = json.loads(meta_path.read_text())
    meta["attributes"]["pixloc_map"]["num_rows"] = 10 ** 12
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(StoreError, match="contradict"):
        open_store(store)


def test_version_1_store_is_refused_with_the_fix(stairs, tmp_path):
    job, _, _ = stairs
    store = _copy_store(job, tmp_path)
    meta = json.loads((store / "zarr.json").read_text())
    meta["attributes"]["pixloc_map"]["version"] = 1
    (store / "zarr.json").write_text(json.dumps(meta))
    with pytest.raises(StoreError, match="--overwrite"):
        open_store(store)


# --- summaries -----------------------------------------------------------------------------

def test_missing_ground_truth_gives_no_nan(stairs, tmp_path):
    """Before: one query without ground truth made every median NaN and evaluation.json invalid."""
    job, queries, _ = stairs
    records = run_sync(plan_localization(job, queries[:3], tmp_path / "out"))
    gt = {q.name: q.cam_from_world_gt for q in queries[:3]}
    gt[queries[0].name] = np.full((3, 4), np.nan)
    summary = evaluate(records, gt)
    assert summary["all"]["no_ground_truth"] == 1 and summary["all"]["refined"]["count"] == 2
    assert np.isfinite(summary["all"]["refined"]["median_t"])
    text = to_json(summary)
    json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    only_failures = evaluate([], {q.name: q.cam_from_world_gt for q in queries[:2]})
    assert only_failures["all"]["refined"]["median_t"] is None and only_failures["all"]["refined"]["no_pose"] == 2
    json.loads(to_json(only_failures), parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))


# --- models and batches ----------------------------------------------------------------------

def test_model_without_confidences_localizes_and_reports(shared, tmp_path):
    """Before: --model photometric crashed localization and the report with KeyError: 'confidences'."""
    from workflows.report import make_report
    root = shared / "data" / "7scenes_stairs"
    conf = FeatureConfig(model="photometric", resize=160, image_scales=(1,))
    build_map(rgbd_scene(read_7scenes(root, [2]), method="frames", stride=32), tmp_path / "p.zarr", conf)
    queries = load_queries("7scenes", root, sequences=(1,))[:2]
    job = LocalizationJob(str(tmp_path / "p.zarr"), conf, "photometric", LCONF, GlobalDescriptors(k=3))
    records = run_sync(plan_localization(job, queries, tmp_path / "out"))
    assert all(r["per_level"] and "KeyError" not in r["reason"] for r in records)
    page = make_report(tmp_path / "out", queries, num_examples=1).read_text()
    assert page.count("data:image/jpeg") >= 1  # the examples, drawn without a confidence map


def test_one_query_error_does_not_fail_the_shard(stairs, tmp_path, monkeypatch):
    """Before: one uncaught error in Localizer.localize_batch left the whole shard without records."""
    from pipeline.localization import refine as loc
    job, queries, _ = stairs
    real = loc.Localizer.predict

    def predict(self, rgb, k):
        if rgb.mean() == predict.bad_mean:
            raise RuntimeError("simulated network failure")
        return real(self, rgb, k)
    from pipeline.images import read_image
    predict.bad_mean = read_image(queries[1].path).mean()
    monkeypatch.setattr(loc.Localizer, "predict", predict)
    job = dataclasses.replace(job, retrieval=PairsFile(pairs=str(tmp_path / "pairs.txt")))
    names = [str(n) for n in open_store(job.store)["images/name"][:]]
    (tmp_path / "pairs.txt").write_text("".join(f"{q.name} {names[0]}\n{q.name} {names[1]}\n" for q in queries[:3]))
    records = run_sync(plan_localization(job, queries[:3], tmp_path / "out"))
    assert len(records) == 3
    assert "simulated network failure" in records[1]["reason"]
    assert all(r["per_level"] for r in (records[0], records[2]))


# --- jobs and runs -------------------------------------------------------------------------

def test_bad_job_settings_are_refused_before_any_query(stairs, tmp_path):
    """Before: an unknown retrieval method fell back to global retrieval silently."""
    job, queries, _ = stairs
    recorded = job.to_dict()
    for bad, text in [({**recorded, "retrieval": {"method": "netvlad"}}, "Unknown retrieval method 'netvlad'"),
                      ({**recorded, "prior": {"name": "best"}}, "Unknown prior 'best'"),
                      ({**recorded, "prior": {"name": "top1", "point_selection": "inliers"}},
                       "unknown key 'point_selection'")]:
        with pytest.raises(ValueError, match=text):
            LocalizationJob.from_dict(bad)
    for bad, text in [(dataclasses.replace(job, prior=Hloc(str(tmp_path / "no.pkl"), point_selection="best")),
                       "Unknown point selection"),
                      (dataclasses.replace(job, prior=OtherPipeline(str(tmp_path / "no.txt"))), "does not exist"),
                      (dataclasses.replace(job, prior=OtherPipeline()), "--prior poses needs --prior-poses FILE")]:
        with pytest.raises(ValueError, match=text):
            plan_localization(bad, queries, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_dry_run_writes_nothing_and_the_real_run_then_works(stairs, tmp_path):
    """Before: --dry-run wrote job.json, so the real run with other options was refused."""
    job, queries, root = stairs
    out = tmp_path / "out"
    args = ["localize", "7scenes", root, "--query-sequences", "1", "--store", job.store, "--output", out, "--sync",
            "--iters", "5", "--num-dbs", "2"]
    dry = pixloc(*args, "--dry-run")
    assert dry.returncode == 0, dry.stderr
    assert "model   pixloc-lite0" in dry.stdout and not out.exists()
    run = pixloc(*args[:-4], "--iters", "6", "--num-dbs", "2")
    assert run.returncode == 0, run.stderr
    assert "all                          result   n=3" in run.stdout  # the evaluate table, as ground truth exists
    stored = json.loads((out / "job.json").read_text())
    assert stored["job"]["localizer"]["num_iters"] == 6
    assert Path(stored["job"]["store"]).is_absolute() and Path(stored["job"]["store"]) == Path(job.store).resolve()
    # poses.txt has a line per query; failed.txt lists those without a verified pose
    lines = (out / "poses.txt").read_text().splitlines()
    failed = (out / "failed.txt").read_text().splitlines()
    assert len(lines) == 3 and len(failed) == sum(not r["success"] for r in read_records(out / "records.jsonl"))
    # a finished run reruns as a no-op, and says so
    again = pixloc(*args[:-4], "--iters", "6", "--num-dbs", "2")
    assert again.returncode == 0 and "3 of 3 queries already done in" in again.stdout
    assert "nothing to do" in again.stdout and "(all reused)" in again.stdout
    # the report from another directory (absolute paths in job.json)
    rep = pixloc("report", "7scenes", root, "--query-sequences", "1", "--output", out, "--preset", "7scenes",
                 "--units", "m", cwd=tmp_path)
    assert rep.returncode == 0, rep.stderr
    assert "within 0.05 m, 5&deg;" in (out / "report.html").read_text()  # the preset's thresholds, in metres


def test_rerun_retries_fixed_inputs_unless_keep_failures(stairs, tmp_path):
    """Before: a failed query was stored in a finished shard and a rerun returned it in 0 s."""
    job, queries, _ = stairs
    image = tmp_path / "q.jpg"
    query = dataclasses.replace(queries[0], path=image)  # missing for now
    out = tmp_path / "out"
    first = run_sync(plan_localization(job, [query, queries[1]], out, shard_size=2))  # reruns keep its shard size
    assert "missing" in first[0]["reason"]
    image.write_bytes(queries[0].path.read_bytes())  # the user fixes the input
    keep = plan_localization(job, [query, queries[1]], out, keep_failures=True)
    assert keep.counts()["to_run"] == 0
    plan = plan_localization(job, [query, queries[1]], out)
    assert plan.counts() == {"queries": 2, "shards": 1, "to_run": 1, "retried": 1, "reused_queries": 1,
                             "reused_shards": 0}
    second = run_sync(plan)
    assert second[0]["references"] and "missing" not in second[0]["reason"]
    assert second[1] == first[1]  # not redone
    assert plan_localization(job, [query, queries[1]], out).counts()["to_run"] == 0


def test_a_second_run_into_the_same_output_is_refused(stairs, tmp_path):
    job, queries, _ = stairs
    out = tmp_path / "out"
    with output_lock(out):
        with pytest.raises(OutputLocked, match="in use by another pixloc run"):
            run_sync(plan_localization(job, queries[:1], out))
    (out / ".pixloc.lock").write_text(f"{os.uname().nodename} 999999999")  # a killed run's lock
    assert len(run_sync(plan_localization(job, queries[:1], out))) == 1


def test_overwrite_redoes_a_run_with_another_job(stairs, tmp_path):
    job, queries, _ = stairs
    out = tmp_path / "out"
    run_sync(plan_localization(job, queries[:1], out))
    other = dataclasses.replace(job, localizer=dataclasses.replace(LCONF, num_iters=3))
    with pytest.raises(ValueError, match="--overwrite"):
        plan_localization(other, queries[:1], out)
    records = run_sync(plan_localization(other, queries[:1], out, overwrite=True))
    assert all(lvl["iterations"] <= 3 for lvl in records[0]["per_level"])


# --- other pipelines' inputs and caches ------------------------------------------------------

def test_hloc_log_with_clusters_takes_the_best_cluster():
    """Before: logs written with covisibility clustering reported 'PnP failed' for every query."""
    ret = {"success": True, "qvec": np.array([1.0, 0, 0, 0]), "tvec": np.array([1.0, 2, 3]), "num_inliers": 2,
           "inliers": np.array([True, True, False])}
    cluster = {"db": [7, 9], "PnP_ret": ret, "keypoint_index_to_db": (np.arange(3), [(11, [0]), (12, [1]), (13, [0])])}
    log = parse_loc("q.jpg", {"db": [7, 9, 4], "best_cluster": 1, "covisibility_clustering": True,
                              "log_clusters": [{"db": [4], "PnP_ret": {"success": False}}, cluster]})
    assert log.success and log.num_inliers == 2 and log.db_ids == [7, 9]
    np.testing.assert_allclose(log.cam_from_world[:, 3], [1, 2, 3])
    assert not parse_loc("q.jpg", {"db": [1], "best_cluster": None, "log_clusters": []}).success


def test_two_model_files_with_one_name_never_share_features(tmp_path):
    """Before: feature_key used the file stem only."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "a" / "model.pt").write_bytes(b"one")
    (tmp_path / "b" / "model.pt").write_bytes(b"two")
    keys = {feature_key(FeatureConfig(model=str(tmp_path / d / "model.pt"))) for d in "ab"}
    assert len(keys) == 2 and all(k.startswith("model-") for k in keys)


def test_synthetic_dataset_is_regenerated_when_its_config_changes(tmp_path):
    """Before: a generated dataset was reused whatever its config."""
    from pipeline.scene import CameraRecord
    from pipeline.data.synthetic import SyntheticConfig, ensure_generated, read_views
    cam = CameraRecord("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
    ensure_generated(tmp_path, SyntheticConfig(seed=1), 2, 1, cam)
    stamp = (tmp_path / "cameras.json").stat().st_mtime_ns
    ensure_generated(tmp_path, SyntheticConfig(seed=1), 2, 1, cam)
    assert (tmp_path / "cameras.json").stat().st_mtime_ns == stamp  # same config: reused
    ensure_generated(tmp_path, SyntheticConfig(seed=1), 3, 1, cam)
    assert len([v for v in read_views(tmp_path) if v.tags["split"] == "mapping"]) == 3


def test_evaluate_takes_thresholds_and_a_ground_truth_file(stairs, tmp_path):
    job, queries, root = stairs
    out = tmp_path / "out"
    run_sync(plan_localization(job, queries[:2], out))
    from pipeline.scene import rotmat_to_qvec
    (tmp_path / "list.txt").write_text("".join(f"{q.name} PINHOLE 640 480 525 525 320 240\n" for q in queries[:2]))
    (tmp_path / "gt.txt").write_text("".join(
        " ".join([q.name, *map(str, rotmat_to_qvec(q.cam_from_world_gt[:, :3])), *map(str, q.cam_from_world_gt[:, 3])])
        + "\n" for q in queries[:2]))
    res = pixloc("evaluate", "list", tmp_path / "list.txt", "--query-images", root, "--output", out,
                 "--ground-truth", tmp_path / "gt.txt", "--thresholds", "0.05,1", "0.25,2")
    assert res.returncode == 0, res.stderr
    doc = json.loads((out / "evaluation.json").read_text())
    summary = doc["conditions"]
    assert summary["all"]["result"]["count"] == 2
    assert {"recall@0.05m,1.0deg", "recall@0.25m,2.0deg"} <= set(summary["all"]["result"])
    # one record per query with its errors and outcome (before: bare arrays without names)
    assert [q["name"] for q in doc["queries"]] == [q.name for q in queries[:2]]
    assert all(q["outcome"] in ("refined", "rejected", "failed") and "t" in q["result"] for q in doc["queries"])
    assert doc["thresholds"] == [[0.05, 1.0], [0.25, 2.0]]
    assert "nan" not in res.stdout


def test_min_track_length_is_an_option_and_what_it_drops_is_counted(stairs, tmp_path):
    """Before: the fixed minimum track length (3) silently dropped points of small maps."""
    job, queries, root = stairs
    three = run_sync(plan_localization(job, queries[:1], tmp_path / "a"))[0]
    two_job = dataclasses.replace(job, localizer=dataclasses.replace(LCONF, min_track_length=2))
    two = run_sync(plan_localization(two_job, queries[:1], tmp_path / "b"))[0]
    assert three["filters"]["short_tracks"] > 0 and two["filters"]["short_tracks"] == 0
    assert two["num_points"] == three["num_points"] + three["filters"]["short_tracks"]
    out = pixloc("localize", "7scenes", root, "--query-sequences", "1", "--query-names", queries[0].name,
                 "--store", job.store, "--output", tmp_path / "c", "--sync", "--iters", "3",
                 "--min-track-length", "2")
    assert out.returncode == 0, out.stderr
    assert "0 points seen by fewer than 2 map images left out" in out.stdout


def test_hypotheses_keep_the_most_confident_refinement(stairs):
    """Before: the lowest mean cost won, over different sets of valid points."""
    from pipeline.localization.refine import Localizer
    from pipeline.store.reader import MapReader
    from pipeline.models import localization_model
    from pipeline.localization.shard import localize_queries, prepare_query
    job, queries, _ = stairs
    hjob = dataclasses.replace(job, prior=ReferenceHypotheses(3))
    refiner, digest = localization_model(job.model)
    reader = MapReader(job.store, FCONF, digest)
    localizer = Localizer(refiner.extractor, refiner.solvers, reader, LCONF)
    for q in queries[:2]:
        candidates = localizer.localize_batch(prepare_query(hjob, reader, localizer, q))
        (chosen,) = localize_queries(hjob, reader, localizer, [q])
        assert len(candidates) == 3
        assert chosen.confidence == max(c.confidence for c in candidates)
        np.testing.assert_allclose(chosen.refined, max(candidates, key=lambda c: c.confidence).refined, atol=1e-6)


def test_search_refines_the_top1_start_first_and_searches_only_where_it_is_not_verified(stairs, monkeypatch):
    """Where the top-1 refinement is verified (here: verification off, every converged refinement is),
    the search is exactly ``top1`` and screens nothing; where it is not (default verification: 7-Scenes
    from retrieval, ~46 deg off, is rejected), the search screens its starts and the top-1 refinement
    stays one of the candidates."""
    from pipeline.localization.refine import Localizer
    from pipeline.store.reader import MapReader
    from pipeline.localization.shard import localize_queries
    from pipeline.models import localization_model
    from pipeline.localization.verify import VerificationConfig
    job, queries, _ = stairs
    refiner, digest = localization_model(job.model)
    reader = MapReader(job.store, FCONF, digest)
    calls = []
    real = Localizer.localize_batch
    monkeypatch.setattr(Localizer, "localize_batch", lambda self, items: calls.append(len(items)) or real(self, items))
    off = dataclasses.replace(LCONF, verification=VerificationConfig(enabled=False))
    for lconf, searched in ((off, False), (LCONF, True)):
        localizer = Localizer(refiner.extractor, refiner.solvers, reader, lconf)
        top1 = localize_queries(dataclasses.replace(job, localizer=lconf), reader, localizer, queries[:2])
        calls.clear()
        search = localize_queries(dataclasses.replace(job, localizer=lconf, prior=Search()), reader, localizer,
                                  queries[:2])
        # the two top-1 starts, first, in one batch, with their rival starts (verification.rivals) where verifying
        assert calls[0] == 2 * (1 + (lconf.verification.rivals if lconf.verification.enabled else 0))
        if not searched:
            assert calls == [2] and all(r.success for r in search)
            for a, b in zip(top1, search):
                np.testing.assert_allclose(b.refined, a.refined, atol=1e-9)
                assert "the top-1 start was verified" in b.notes[-1]
        else:
            assert not any(r.success for r in top1) and calls[1] == 2 * 28  # then every start screened
            for a, b in zip(top1, search):
                assert "the top-1 start was not verified; 28 starting poses screened" in b.notes[-1]
                assert b.confidence >= a.confidence  # the top-1 refinement was among the candidates
