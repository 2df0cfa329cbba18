"""Fault catalogue, round three, stores and remote parts: every entry of a store is read through one
reader (``pipeline.store.location.LocalObjects``) that refuses what is not a regular file before a byte
is read, and never blocks; attributes are checked for type, range and agreement with the arrays at
open; damaged metadata and absent dense chunks are named; a store holds only its own files; a remote
endpoint or scheduler that accepts and never answers stops the command within a documented bound."""

import json
import os
import random
import re
import resource
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from pipeline.store import location
from pipeline.store.check import check_store
from pipeline.store.feature_groups import feature_key
from pipeline.store.layout import StoreError, StoreReadError, open_store
from pipeline.store.reader import MapReader
from workflows.localize import plan_localization, run_sync

from .conftest import FCONF, ROOT, pixloc
from .test_stores import _image_files

KINDS = ("symlink to /dev/zero", "fifo", "folder", "symlink loop", "socket")


def _replace(path: Path, kind: str) -> None:
    """Put an entry of ``kind`` where the file ``path`` was."""
    path.unlink()
    if kind == "symlink to /dev/zero":
        path.symlink_to("/dev/zero")
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
    elif kind == "symlink loop":
        path.symlink_to(path.name)
    elif kind == "socket":  # bound at a short path (AF_UNIX paths are short), then moved in place
        short = Path(tempfile.mkdtemp()) / "s"
        s = socket.socket(socket.AF_UNIX)
        s.bind(str(short))
        s.close()
        os.rename(short, path)


def _limited():
    """A child process's address space, capped: reading a device without end fails there, not the machine."""
    resource.setrlimit(resource.RLIMIT_AS, (6 * 2**30, 6 * 2**30))


@pytest.mark.parametrize("kind", KINDS)
def test_a_store_entry_that_is_not_a_regular_file_is_named_never_read(stairs, tmp_path, kind):
    """Before: a feature shard replaced by a symlink to /dev/zero made check-store read until the
    kernel killed it at 20.9 GB resident; a FIFO would block it for ever."""
    stairs.copy(tmp_path)
    store = tmp_path / "copy.zarr"
    victim = _image_files(store, f"features/{feature_key(FCONF)}/s0/features", 1)[0]
    _replace(victim, kind)
    names = [str(n) for n in open_store(store)["images/name"][:]]
    t0 = time.time()
    out = subprocess.run([sys.executable, "-m", "workflows.cli", "check-store", str(store)], capture_output=True,
                         text=True, timeout=240, preexec_fn=_limited, cwd=tmp_path,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 1, out.stderr[-800:]  # 1: the check ran and found damage
    assert time.time() - t0 < 200
    key = victim.relative_to(store).as_posix()
    assert key in out.stdout and names[1] in out.stdout and "bad chunk" in out.stdout, out.stdout
    # the reader of every store file, asked directly: an error naming it, at once
    from zarr.core.buffer import default_buffer_prototype
    from zarr.core.sync import sync
    objects = location.zarr_store(store, read_only=True)
    with pytest.raises(location.StoreObjectError, match=re.escape(str(victim))):
        sync(objects.get(key, default_buffer_prototype()))
    assert not sync(objects.exists(key))


def test_random_entries_replaced_by_other_file_types_fail_their_queries_with_the_file_named(stairs, tmp_path):
    """Localization reads a damaged reference's rows through the same reader: the queries that use
    it fail with the file named, the others are localized."""
    job = stairs.copy(tmp_path)
    store = tmp_path / "copy.zarr"
    first = run_sync(plan_localization(job, stairs.queries[:1], tmp_path / "first"))
    names = [str(n) for n in open_store(store)["images/name"][:]]
    ref = names.index(first[0]["references"][0])
    rng = random.Random(3)
    victims = _image_files(store, f"features/{feature_key(FCONF)}/s0/features", ref)
    _replace(victims[0], rng.choice(["symlink to /dev/zero", "fifo", "folder"]))
    from pipeline.store import reader as map_reader
    map_reader.forget_readers()
    records = run_sync(plan_localization(stairs.unverified(job), stairs.queries[:1], tmp_path / "out"))
    assert not records[0]["success"] and victims[0].name in records[0]["reason"], records[0]["reason"]


@pytest.mark.parametrize("change, words", [
    ({"num_points": 1}, "points/xyz holds"), ({"num_points": True}, "num_points"), ({"version": "3"}, '"3"'),
    ({"num_images": "4"}, "num_images"), ({"chunk_rows": 0}, "rows"), ({"scene_observations": -1}, "scene_obs"),
    ({"source": [1]}, "source"), ({"num_rows": 1.5}, "num_rows")])
def test_map_attributes_are_checked_for_type_range_and_the_arrays_at_open(stairs, tmp_path, change, words):
    """Before: num_points 1 (or true) passed check-store and localize died with an IndexError in
    reader.observations; version "3" said 'has version 3; this code reads version 3'."""
    job = stairs.copy(tmp_path)
    header = tmp_path / "copy.zarr" / "zarr.json"
    meta = json.loads(header.read_text())
    meta["attributes"]["pixloc_map"].update(change)
    header.write_text(json.dumps(meta))
    with pytest.raises(StoreError, match=words):
        check_store(job.store)
    with pytest.raises(StoreError, match=words):
        plan_localization(job, stairs.queries[:1], tmp_path / "out")


@pytest.mark.parametrize("change", [{"dims": [True, 64, 32]}, {"dims": "128"}, {"dims": []}, {"pca": -1},
                                    {"pca": "48"}])
def test_feature_group_attributes_are_checked_at_open(stairs, tmp_path, change):
    job = stairs.copy(tmp_path)
    header = tmp_path / "copy.zarr" / "features" / feature_key(FCONF) / "zarr.json"
    meta = json.loads(header.read_text())
    target = meta["attributes"] if "dims" in change else meta["attributes"]["config"]
    target.update(change)
    header.write_text(json.dumps(meta))
    report = check_store(job.store)
    assert not report.ok and "no readable config or dims" in report.summary()
    with pytest.raises(StoreError, match="no readable config or dims"):
        MapReader(job.store, FCONF)


def test_every_metadata_file_truncated_is_named(stairs, tmp_path):
    """Before: a truncated features/<group>/zarr.json gave 'pixloc: error: Expecting value: line 18
    column 6 (char 300)' from check-store, --repair, localize and build-map, with no file named."""
    stairs.copy(tmp_path, "base.zarr")
    base = tmp_path / "base.zarr"
    headers = sorted(p.relative_to(base) for p in base.rglob("zarr.json"))
    for k, key in enumerate(random.Random(7).sample(headers, 8)):
        store = tmp_path / f"m{k}.zarr"
        shutil.copytree(base, store)
        raw = (store / key).read_bytes()
        (store / key).write_bytes(raw[: len(raw) // 2])
        try:
            report = check_store(store)
        except (StoreError, location.StoreObjectError) as e:
            assert str(store / key) in str(e) and "not JSON" in str(e), str(e)
        else:
            assert not report.ok and str(key.parent) in report.summary(), report.summary()


def test_a_consolidated_copy_that_is_missing_is_named_not_read_as_zeros(stairs, tmp_path):
    """Before: a deleted shard of features/<group>/global_all was read as zeros: every query failed
    'no retrieval match' and the file was never named."""
    job = stairs.copy(tmp_path)
    group = tmp_path / "copy.zarr" / "features" / feature_key(FCONF)
    chunk = next(p for p in (group / "global_all").rglob("*") if p.is_file() and p.name != "zarr.json")
    chunk.unlink()
    report = check_store(job.store)
    assert not report.ok and "global_all" in report.summary() and "missing" in report.summary()
    with pytest.raises(StoreReadError, match="global_all"):
        MapReader(job.store, FCONF)


def test_outputs_inside_a_store_are_refused_and_overwrite_keeps_files_it_did_not_write(stairs, tmp_path):
    """Before: localize --output inside a store was accepted, and a later build-map --overwrite of the
    store erased the results and the user's files without a word."""
    job = stairs.copy(tmp_path)
    store = tmp_path / "copy.zarr"
    with pytest.raises(ValueError, match="inside the map store"):
        plan_localization(job, stairs.queries[:1], store / "features" / "results")
    (store / "images" / "notes.txt").write_text("mine")
    report = check_store(job.store)
    assert "images/notes.txt" in report.summary()
    from pipeline.mapping.depth import rgbd_scene
    from pipeline.mapping.readers.rgbd import read_7scenes
    from pipeline.store.structure import create_store
    scene = rgbd_scene(read_7scenes(stairs.root, [2]), method="frames", stride=24)
    with pytest.raises(StoreError, match="notes.txt"):
        create_store(store, scene, overwrite=True)
    assert (store / "images" / "notes.txt").read_text() == "mine"


def test_two_builds_with_one_work_folder_are_refused(shared, tmp_path):
    """Before: two build-map runs of different stores with one --work-dir failed in COLMAP and with
    a RuntimeError traceback."""
    from workflows.locks import work_dir_lock
    m = shared / "data" / "maupertuis"
    with work_dir_lock(tmp_path / "work"):
        out = pixloc("build-map", "colmap", m / "reconstruction", "--images", m / "images", "--store",
                     tmp_path / "b.zarr", "--work-dir", tmp_path / "work", "--resize", 160, "--sync")
    assert out.returncode == 2 and "work folder" in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert not (tmp_path / "b.zarr").exists()


class SilentServer:
    """A TCP listener on 127.0.0.1 that accepts and never answers, for at most ``seconds``."""

    def __init__(self, seconds: float = 120.0):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(64)
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.held, self.end = [], time.time() + seconds
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        while time.time() < self.end:
            try:
                self.held.append(self.sock.accept()[0])
            except (socket.timeout, OSError):
                continue

    def close(self):
        self.end = 0
        self.thread.join()
        for c in self.held:
            c.close()
        self.sock.close()


@pytest.fixture
def silent():
    server = SilentServer()
    yield server
    server.close()


def test_the_storage_timeouts_are_bounded_by_default():
    """The documented default (docs/cluster.md): connect 10 s, read 20 s, two attempts."""
    options = location._options("s3")["config_kwargs"]
    worst = options["connect_timeout"] + options["read_timeout"] * options["retries"]["total_max_attempts"]
    assert worst <= 60


@pytest.mark.parametrize("command", ["check-store", "localize"])
def test_an_object_store_that_accepts_and_never_answers_stops_the_command(silent, tmp_path, command):
    """Before: check-store and localize printed nothing for 432-434 s, then a ReadTimeoutError."""
    pytest.importorskip("s3fs")
    env = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1",
           "AWS_ENDPOINT_URL": f"http://127.0.0.1:{silent.port}"}
    timeouts = json.dumps({"config_kwargs": {"connect_timeout": 2, "read_timeout": 2}})
    args = (["check-store", "s3://maps/m.zarr"] if command == "check-store" else
            ["localize", "list", tmp_path / "q.txt", "--query-images", tmp_path, "--store", "s3://maps/m.zarr",
             "--output", tmp_path / "out", "--sync"])
    (tmp_path / "q.txt").write_text("a.jpg PINHOLE 64 48 50 50 32 24\n")
    t0 = time.time()
    out = pixloc(*args, "--storage-options", timeouts, env=env, timeout=120)
    took = time.time() - t0
    assert out.returncode == 2 and "s3://maps/m.zarr" in out.stderr and "timeouts" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr and took < 60, (took, out.stderr)


def test_a_bucket_that_does_not_exist_is_named(shared, tmp_path, monkeypatch):
    """Before: 'The specified bucket does not exist', without the store's URL."""
    from pipeline.mapping.readers.colmap import read_colmap
    from pipeline.store.structure import create_store
    from workflows.s3_server import CREDENTIALS, ServerUnavailable, moto_server
    try:
        server = moto_server()
        endpoint = server.__enter__()
    except ServerUnavailable as e:
        pytest.skip(str(e))
    try:
        env = {**CREDENTIALS, "AWS_ENDPOINT_URL": endpoint}
        out = pixloc("check-store", "s3://nosuchbucket/m.zarr", env=env, timeout=120)
        assert out.returncode == 2 and "s3://nosuchbucket/m.zarr" in out.stderr, out.stderr
        for k, v in env.items():
            monkeypatch.setenv(k, v)
        m = shared / "data" / "maupertuis"
        with pytest.raises((StoreError, location.StoreLocationError), match="s3://nosuchbucket/m.zarr"):
            create_store("s3://nosuchbucket/m.zarr", read_colmap(m / "reconstruction", m / "images"))
    finally:
        server.__exit__(None, None, None)


def test_a_scheduler_that_accepts_and_never_answers_or_a_damaged_scheduler_file(silent, tmp_path, monkeypatch):
    """Before: a truncated or empty scheduler file gave an AssertionError traceback from distributed,
    and an address that accepts and stays silent waited without bound."""
    from workflows import executor
    monkeypatch.setattr(executor, "SCHEDULER_TIMEOUT_S", 2.0)
    t0 = time.time()
    with pytest.raises(executor.SchedulerError, match="no Dask scheduler answered"):
        with executor.dask_client(f"tcp://127.0.0.1:{silent.port}"):
            pass
    assert time.time() - t0 < 20
    for text, words in (('{"address": "tcp://127.0.0.1:1"', "not valid JSON"), ("{}", "no scheduler address"),
                        ('{"address": 7}', "no scheduler address")):
        path = tmp_path / "scheduler.json"
        path.write_text(text)
        with pytest.raises(ValueError, match=words):
            with executor.dask_client(str(path)):
                pass


def test_a_scheduler_killed_during_a_run_is_one_line_and_the_rerun_resumes(cli_run, tmp_path):
    """Before: three tracebacks (CommClosedError, CancelledError, FutureCancelledError) where one line is right."""
    from workflows.process_cluster import DASK, ProcessCluster, wait_for
    if not DASK.exists():
        pytest.skip("the dask command is not installed next to this Python")
    args = [str(a) for a in cli_run.args if a != "--sync"]
    args[args.index("--output") + 1] = str(tmp_path / "out")
    procs = ProcessCluster(tmp_path, ("w0",), timeout=60)
    try:
        run = subprocess.Popen([sys.executable, "-m", "workflows.cli", *args, "--scheduler", str(procs.sched)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONPATH": str(ROOT)})
        wait_for(lambda: (tmp_path / "out" / "job.json").exists() or run.poll() is not None, 120)
        procs.kill("scheduler")
        _, stderr = run.communicate(timeout=180)
    finally:
        procs.close()
    assert run.returncode == 2, stderr[-2000:]
    assert "Traceback" not in stderr and "went away during the run" in stderr, stderr[-2000:]
    rerun = pixloc(*args, "--sync")
    assert rerun.returncode == 0, rerun.stderr[-1000:]
    assert len((tmp_path / "out" / "poses.txt").read_text().splitlines()) == 2
