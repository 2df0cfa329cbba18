"""Map building through the workflow: a real Dask cluster, killed workers, interrupted runs."""

import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from pipeline.mapping.features import FeatureConfig
from pipeline.mapping.readers.colmap import read_colmap
from pipeline.store.feature_groups import feature_key
from pipeline.store.layout import DONE, open_store
from tests.pipeline.helpers import assert_same_store
from workflows.build_map import plan_build, run_dask, run_sync
from workflows.process_cluster import DASK, ProcessCluster, wait_for

CONF = FeatureConfig(resize=512, image_scales=(1,))  # the size does not matter to scheduling and resuming
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def scene(shared):
    root = shared / "data" / "maupertuis"
    return read_colmap(root / "reconstruction", root / "images").repeated(4)  # 16 images


@pytest.fixture(scope="module")
def reference(scene, tmp_path_factory):
    """The synchronous build, which every other build must equal exactly."""
    path = tmp_path_factory.mktemp("sync") / "map.zarr"
    results = run_sync(plan_build(scene, path, CONF))
    assert [r.status for r in results] == ["done"] * 16
    return path


def done_count(path) -> int:
    try:
        return int((open_store(path)[f"features/{feature_key(CONF)}/status"][:] == DONE).sum())
    except Exception:  # the store is still being created
        return 0


@pytest.fixture
def cluster(tmp_path):
    """A scheduler and two worker processes ("a", "b") on 127.0.0.1, started with the dask CLI."""
    if not DASK.exists():
        pytest.skip("the dask command is not installed next to this Python")
    procs = ProcessCluster(tmp_path, ("a", "b"), timeout=60)
    client = procs.client()
    yield client, {"a": procs.procs["a"], "b": procs.procs["b"]}
    client.close()
    procs.close()


def test_distributed_build_equals_sync(scene, reference, cluster, tmp_path):
    client, _ = cluster
    path = tmp_path / "map.zarr"
    results = run_dask(plan_build(scene, path, CONF), client)
    assert sorted(r.index for r in results) == list(range(16)) and {r.status for r in results} == {"done"}
    assert {w["name"] for w in client.scheduler_info()["workers"].values()} == {"a", "b"}
    assert_same_store(reference, path)


def test_killed_worker_mid_build(scene, reference, cluster, tmp_path):
    client, workers = cluster
    path = tmp_path / "map.zarr"
    outcome = {}
    runner = threading.Thread(target=lambda: outcome.update(results=run_dask(plan_build(scene, path, CONF), client)))
    runner.start()
    wait_for(lambda: done_count(path) >= 3)
    workers["a"].send_signal(signal.SIGKILL)  # the scheduler reschedules its tasks on b
    killed_at = done_count(path)
    runner.join(300)
    assert "results" in outcome and killed_at < 16  # killed mid-build
    assert done_count(path) == 16
    assert_same_store(reference, path)


def test_interrupted_build_resumes_only_missing_images(scene, reference, tmp_path):
    path = tmp_path / "map.zarr"
    script = (
        "import sys; sys.path.insert(0, sys.argv[1])\n"
        "from tests.workflows.test_build_map import CONF\n"
        "from pipeline.mapping.readers.colmap import read_colmap\n"
        "from workflows.build_map import plan_build, run_sync\n"
        "root = sys.argv[3]\n"
        "scene = read_colmap(root + '/reconstruction', root + '/images').repeated(4)\n"
        "run_sync(plan_build(scene, sys.argv[2], CONF))\n")
    shared_root = str(scene.images[0].path.parent.parent)
    proc = subprocess.Popen([sys.executable, "-c", script, str(ROOT), str(path), shared_root])
    wait_for(lambda: done_count(path) >= 4)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done_before = done_count(path)
    assert 4 <= done_before < 16
    status = open_store(path)[f"features/{feature_key(CONF)}/status"][:]
    missing = sorted(int(i) for i in (status != DONE).nonzero()[0])
    results = run_sync(plan_build(scene, path, CONF))
    assert sorted(r.index for r in results) == missing  # nothing finished is redone
    assert {r.status for r in results} == {"done"}
    assert_same_store(reference, path)


def test_dry_run_prints_the_plan(shared, tmp_path):
    root = shared / "data" / "maupertuis"
    out = subprocess.run([sys.executable, "-m", "workflows.cli", "build-map", "colmap", str(root / "reconstruction"),
                          "--images", str(root / "images"), "--store", str(tmp_path / "m.zarr"), "--dry-run"],
                         capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert "4 images, 1039 points, 3355 observations" in out.stdout
    assert "4 images to extract in 4 tasks" in out.stdout and "expected size" in out.stdout
    assert not (tmp_path / "m.zarr").exists()
    sizes = []
    for extra in ([], ["--sift", "1600"]):  # the SIFT descriptors: 128 bytes per observation before compression
        out = subprocess.run([sys.executable, "-m", "workflows.cli", "build-map", "colmap",
                              str(root / "reconstruction"), "--images", str(root / "images"), "--store",
                              str(tmp_path / "m.zarr"), "--dry-run", *extra], capture_output=True, text=True, cwd=ROOT)
        sizes.append(float(out.stdout.split("expected size")[1].split()[0]))
        assert ("'sift': 1600" in out.stdout) == bool(extra)
    assert abs((sizes[1] - sizes[0]) * 2**20 - 128 * 3355) < 0.1 * 2**20


def test_rgbd_pose_txt_source_plan(shared, tmp_path):
    out = subprocess.run([sys.executable, "-m", "workflows.cli", "build-map", "posetxt",
                          str(shared / "data" / "rgbd_slambook" / "kinect_room"), "--intrinsics", "518", "519",
                          "325.5", "253.5", "--depth-ext", ".pgm", "--rgbd-points", "frames",
                          "--store", str(tmp_path / "k.zarr"), "--dry-run"], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert "1 structure  5 images" in out.stdout
    out = subprocess.run([sys.executable, "-m", "workflows.cli", "build-map", "posetxt", str(tmp_path),
                          "--store", str(tmp_path / "k.zarr"), "--dry-run"], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 2 and "pixloc: error: A posetxt source needs --intrinsics" in out.stderr
    assert "Traceback" not in out.stderr


KINECT_K = ["518", "519", "325.5", "253.5"]  # rgbd_slambook's kinect_room


def build_kinect(root: Path, store: Path, *extra: str) -> subprocess.CompletedProcess:
    """``build-map posetxt`` of a kinect_room folder at 320 px, in this process's Python."""
    return subprocess.run([sys.executable, "-m", "workflows.cli", "build-map", "posetxt", str(root), "--intrinsics",
                           *KINECT_K, "--depth-ext", ".pgm", "--store", str(store), "--sync", "--resize", "320",
                           "--image-scales", "1", *extra], capture_output=True, text=True, cwd=ROOT)


def test_a_held_out_rgbd_frame_is_localized_as_a_posetxt_query(shared, tmp_path):
    """A pose.txt folder is a query source too (before: a map source only, so its held-out frames had no
    query kind with their ground truth): build-map --hold-out one frame, then localize it from the same
    folder with the same intrinsics."""
    root, K = shared / "data" / "rgbd_slambook" / "kinect_room", KINECT_K
    cli = [sys.executable, "-m", "workflows.cli"]
    built = build_kinect(root, tmp_path / "k.zarr", "--hold-out", "color/3.png")
    assert built.returncode == 0, built.stderr
    assert "4 images extracted" in built.stdout
    done = subprocess.run(cli + ["localize", "posetxt", str(root), "--intrinsics", *K, "--query-names", "color/3.png",
                                 "--store", str(tmp_path / "k.zarr"), "--output", str(tmp_path / "out"), "--sync"],
                          capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert "1 query (1 run in" in done.stdout and "0 failed" in done.stdout
    result = next(line for line in done.stdout.splitlines() if line.startswith("all") and " result " in line)
    t, R = float(result.split("median")[1].split("/")[0]), float(result.split("/")[1].split("deg")[0])
    assert t < 0.15 and R < 2.0, result  # against pose.txt's pose: 0.05 m, 0.96 deg at 320 px (0.03 m, 0.46 at 1,024)
    missing = subprocess.run(cli + ["localize", "posetxt", str(root), "--store", str(tmp_path / "k.zarr"),
                                    "--output", str(tmp_path / "o2")], capture_output=True, text=True, cwd=ROOT)
    assert missing.returncode == 2 and "needs --intrinsics" in missing.stderr


def test_an_unknown_model_is_refused_before_the_reconstruction(shared, tmp_path):
    """Before: a triangulated or SfM source ran its reconstruction (minutes), then refused the model."""
    out = subprocess.run([sys.executable, "-m", "workflows.cli", "build-map", "strecha",
                          str(shared / "data" / "strecha" / "fountain-P11"), "--store", str(tmp_path / "m.zarr"),
                          "--model", "nothere.pt", "--dry-run"], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 2 and "Unknown feature model" in out.stderr and "nothere.pt" in out.stderr
    assert not (tmp_path / "m.work").exists()


def _done(store: Path) -> int:
    try:
        root = open_store(store)
        (key,) = list(root["features"].group_keys())
        return int((root[f"features/{key}/status"][:] == DONE).sum())
    except Exception:  # not created yet
        return 0


@pytest.mark.parametrize("kind, folder, images", [
    pytest.param("strecha", "strecha/Herz-Jesus-P8", 8, marks=pytest.mark.slow),  # the same path as sfm's: slow tier
    ("sfm", "sacre_coeur/mapping", 10)])
def test_killed_build_resumes_and_a_finished_build_reruns_as_a_noop(shared, tmp_path, kind, folder, images):
    """Before: pycolmap's SfM and triangulation gave another map on each run, so any rerun failed with
    'holds another map ... pass overwrite'. The work folder's finished reconstruction is now reused. SfM
    is also killed during SIFT and during the mapping first: the reruns redo no finished shard."""
    store = tmp_path / "map.zarr"
    cmd = [sys.executable, "-m", "workflows.cli", "build-map", kind, str(shared / "data" / folder),
           "--store", str(store), "--sync", "--resize", "512", "--image-scales", "1"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    work = tmp_path / "map.work" / ("sfm" if kind == "sfm" else "triangulation")
    shards, log = work / "shards", tmp_path / "map.work" / "build-map.log"
    if kind == "sfm":  # killed during SIFT (shards of 2 images: 5), then during the mapping: no shard redone
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wait_for(lambda: len(list(shards.glob("sift-*.npz"))) >= 1, timeout=400)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        made = {f: f.stat().st_mtime_ns for f in shards.glob("sift-*.npz")}
        assert 1 <= len(made) < 5
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wait_for(lambda: (work / "database.db").exists(), timeout=400)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert not (work / "sfm.json").exists() and len(list(shards.glob("matches-*.npz"))) == 1
        assert f"SIFT features: {len(made)} of 5 shards already made" in log.read_text()
        assert all(f.stat().st_mtime_ns == t for f, t in made.items())
        shard_times = {f: f.stat().st_mtime_ns for f in shards.iterdir()}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_for(lambda: _done(store) >= 1, timeout=400)
    if kind == "sfm":
        said = log.read_text()
        assert "SIFT features: 5 of 5 shards already made" in said and "SIFT matching: 1 of 1 shards" in said
        assert {f: f.stat().st_mtime_ns for f in shards.iterdir()} == shard_times
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    before = _done(store)
    assert 1 <= before < images
    resumed = subprocess.run(cmd, env=env, capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert _done(store) == images
    assert f"{images - before} images extracted, {before} already done" in resumed.stdout
    again = subprocess.run(cmd, env=env, capture_output=True, text=True)
    assert again.returncode == 0, again.stderr[-2000:]
    assert f"All {images} images of {store} already have features" in again.stdout and "nothing to do" in again.stdout
    # --overwrite rebuilds it whole
    over = subprocess.run(cmd + ["--overwrite"], env=env, capture_output=True, text=True)
    assert over.returncode == 0 and f"{images} images extracted, 0 already done" in over.stdout


def test_a_new_reconstruction_for_a_stores_map_names_the_work_folder(shared, tmp_path, monkeypatch, capsys):
    """Before: a store copied without the work folder that built it (or a repair run elsewhere) was
    refused as 'holds another map' by the very command that built it, without saying why: SfM and
    triangulation give another map each run, and only the work folder's finished one is reused.
    Here the second 'reconstruction' is given another map outright (one image fewer)."""
    from workflows import cli, cli_build_map
    root = shared / "data" / "maupertuis"
    full = read_colmap(root / "reconstruction", root / "images")
    scenes = iter([full.subset([0, 1, 2, 3]), full.subset([0, 1, 2])])
    monkeypatch.setattr(cli_build_map, "load_scene", lambda *args, **kwargs: next(scenes))
    argv = ["build-map", "sfm", str(root / "images"), "--store", str(tmp_path / "map.zarr"), "--sync",
            "--resize", "160", "--image-scales", "1"]
    assert cli.main(argv) in (0, None)
    capsys.readouterr()
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert re.search(r"holds another map .* which gives another map each time it runs: a rerun reuses the one "
                     r"finished in its work folder, here .*map\.work\. .*--work-dir", err), err


def test_build_map_into_an_existing_store_adds_a_mapping_session(shared, tmp_path):
    """7-Scenes sequence 2, then sequences 2 and 3 into the same store: the 3 new frames are added
    and only they are extracted; the first session's rows are not rewritten."""
    store = tmp_path / "map.zarr"
    cmd = [sys.executable, "-m", "workflows.cli", "build-map", "7scenes", str(shared / "data" / "7scenes_stairs"),
           "--store", str(store), "--sync", "--resize", "160", "--image-scales", "1", "--rgbd-points", "frames"]
    first = subprocess.run(cmd + ["--sequences", "2"], capture_output=True, text=True, cwd=ROOT)
    assert first.returncode == 0, first.stderr[-2000:]
    root = open_store(store)
    shard = root["features"][next(iter(root["features"].group_keys()))]["s0"]["features"]
    files = {f: f.stat().st_mtime_ns for f in (store / shard.path).rglob("*") if f.is_file() and f.name != "zarr.json"}
    assert len(files) >= 3  # one shard file per image of the first session
    meta = dict(root.attrs["pixloc_map"])
    added = subprocess.run(cmd + ["--sequences", "2", "3"], capture_output=True, text=True, cwd=ROOT)
    assert added.returncode == 0, added.stderr[-2000:]
    assert "3 images extracted, 3 already done" in added.stdout
    new = open_store(store).attrs["pixloc_map"]
    assert new["num_images"] == 6 and new["num_observations"] > meta["num_observations"]
    assert all(f.stat().st_mtime_ns == t for f, t in files.items())  # the first session's shards untouched
    assert _done(store) == 6


def test_an_rgbd_frame_with_a_damaged_depth_map_is_refused_by_name(shared, tmp_path):
    """One truncated depth map of five: the build makes the map of the other four and says which frame it
    refused and why (before: the whole build stopped; then the summary counted the refused frame nowhere);
    a rerun has nothing to do."""
    kinect = shared / "data" / "rgbd_slambook" / "kinect_room"
    root = tmp_path / "kinect"
    for sub in ("color", "depth"):
        (root / sub).mkdir(parents=True)
        for p in (kinect / sub).iterdir():
            (root / sub / p.name).symlink_to(p)
    (root / "pose.txt").symlink_to(kinect / "pose.txt")
    (root / "depth" / "2.pgm").unlink()
    (root / "depth" / "2.pgm").write_bytes((kinect / "depth" / "2.pgm").read_bytes()[:3000])
    built = build_kinect(root, tmp_path / "k.zarr", "--rgbd-points", "frames")
    assert built.returncode == 0, built.stderr
    assert "4 images extracted, 1 already done or refused, 0 failed" in built.stdout
    assert f"refused: color/2.png: depth file {root / 'depth' / '2.pgm'} cannot be decoded" in built.stdout
    assert "[ERROR:" not in built.stderr  # OpenCV's own line stays off the terminal
    root_group = open_store(tmp_path / "k.zarr")
    names = [str(n) for n in root_group["images/name"][:]]
    assert sorted(names) == [f"color/{k}.png" for k in range(1, 6)]
    again = build_kinect(root, tmp_path / "k.zarr", "--rgbd-points", "frames")
    assert again.returncode == 0 and "nothing to do" in again.stdout, again.stdout + again.stderr
