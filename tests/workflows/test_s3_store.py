"""A map store in a bucket: a real S3 API server (moto's standalone server, on 127.0.0.1) and the
real client (s3fs, boto3), no mock of either. The map is built into the bucket by the build's
Dask workers, localized from it by workers of a ``ProcessCluster`` that run in an empty folder
after the build's local folder is gone, checked, damaged one object at a time and repaired."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from workflows.process_cluster import DASK, ProcessCluster
from workflows.s3_server import CREDENTIALS, ServerUnavailable, client, moto_server

ROOT = Path(__file__).resolve().parents[2]
STORE = "s3://maps/hj.zarr"


@pytest.fixture(scope="module")
def s3():
    """The endpoint of a moto S3 server started for this module (and stopped after it), with
    the bucket ``maps``; skipped, with the reason, where the packages or the server are missing."""
    try:
        with moto_server() as endpoint:
            yield endpoint
    except ServerUnavailable as e:
        pytest.skip(str(e))


@pytest.fixture
def env(s3, monkeypatch):
    """Credentials from the usual environment, the endpoint as storage options (what a user sets)."""
    values = {**CREDENTIALS, "PIXLOC_STORAGE_OPTIONS": json.dumps({"endpoint_url": s3}), "OMP_NUM_THREADS": "1"}
    for k, v in values.items():
        monkeypatch.setenv(k, v)
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def pixloc(env, cwd, *args, check=True) -> subprocess.CompletedProcess:
    out = subprocess.run([sys.executable, "-m", "workflows.cli", *map(str, args)], cwd=cwd, env=env,
                         capture_output=True, text=True, timeout=600)
    if check:
        assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    return out


def test_a_map_in_a_bucket_is_built_localized_checked_and_repaired(shared, s3, env, tmp_path):
    if not DASK.exists():
        pytest.skip("the dask command is not installed next to this Python")
    scene = shared / "data" / "strecha" / "Herz-Jesus-P8"
    build_dir, worker_dir = tmp_path / "build", tmp_path / "workers"
    build_dir.mkdir()
    worker_dir.mkdir()
    # the map of 0001, 0002, 0004 and 0005, for the query 0003: what a bucket changes does not depend on the size
    build = ["build-map", "strecha", scene, "--hold-out", "0000.jpg", "0003.jpg", "0006.jpg", "0007.jpg",
             "--store", STORE, "--resize", "512", "--image-scales", "1"]

    # built by the local cluster's workers, each writing its images' objects; the work folder is local
    out = pixloc(env, build_dir, *build, "--workers", "2")
    assert "4 images extracted" in out.stdout
    assert (build_dir / "hj.work" / "build-map.log").is_file() and not (build_dir / "hj.zarr").exists()
    keys = [o["Key"] for o in client(s3).list_objects_v2(Bucket="maps", Prefix="hj.zarr/")["Contents"]]
    assert "hj.zarr/zarr.json" in keys and len(keys) > 50
    assert pixloc(env, build_dir, *build).stdout.count("nothing to do") == 1  # a rerun is a no-op

    # localized on workers that run in another folder, with the build's folder gone from this host
    away = tmp_path / "away"
    build_dir.rename(away)
    cluster = ProcessCluster(tmp_path, ("a", "b"), timeout=60, cwd=worker_dir)
    try:
        out = pixloc(env, tmp_path, "localize", "strecha", scene, "--query-names", "0003.jpg", "--store", STORE,
                     "--output", tmp_path / "out", "--scheduler", cluster.sched)
    finally:
        cluster.close()
    away.rename(build_dir)
    assert "1 refined" in out.stdout, out.stdout
    result = [line for line in out.stdout.splitlines() if line.startswith("all") and " result " in line]
    assert result and "0.25 m, 2 deg: 100.0%" in result[0], out.stdout  # the held-out photo, from the bucket
    record = json.loads((tmp_path / "out" / "records.jsonl").read_text().splitlines()[0])
    assert record["success"] and record["store_io"]["bytes_read"] > 1e5  # its references, from the bucket
    assert json.loads((tmp_path / "out" / "job.json").read_text())["job"]["store"] == STORE
    assert not list(worker_dir.iterdir())  # the workers wrote nothing where they ran

    # checked; then one object's byte flipped and another object deleted: each image named
    out = pixloc(env, tmp_path, "check-store", STORE)
    assert "all chunks verified" in out.stdout
    s3_client = client(s3)
    features = sorted(k for k in keys if "/s0/features/c/" in k)
    flipped, deleted = features[0], features[-1]  # chunks of two images (each named below)
    body = bytearray(s3_client.get_object(Bucket="maps", Key=flipped)["Body"].read())
    body[len(body) // 2] ^= 0xFF
    s3_client.put_object(Bucket="maps", Key=flipped, Body=bytes(body))
    s3_client.delete_object(Bucket="maps", Key=deleted)
    out = pixloc(env, tmp_path, "check-store", STORE, "--repair", check=False)
    assert out.returncode == 1, out.stdout + out.stderr
    bad = [line for line in out.stdout.splitlines() if line.strip().startswith("bad chunk")]
    assert len(bad) == 2 and "2 bad chunks" in out.stdout, out.stdout
    assert len({line.split("(images ")[1].split(")")[0] for line in bad}) == 2  # each names its image
    assert any("checksum" in line for line in bad) and any("missing" in line for line in bad)
    assert "2 images marked pending" in out.stdout

    # the same build command rebuilds only them, and the store is whole again
    out = pixloc(env, build_dir, *build, "--sync")
    assert "2 images extracted, 2 already done" in out.stdout, out.stdout
    assert "all chunks verified" in pixloc(env, tmp_path, "check-store", STORE).stdout

    # a truncated metadata object is named by its URL, as a local file is by its path (test_round3_stores)
    group = next(k for k in keys if k.endswith("/s0/features/zarr.json"))
    body = s3_client.get_object(Bucket="maps", Key=group)["Body"].read()
    s3_client.put_object(Bucket="maps", Key=group, Body=body[: len(body) // 2])
    out = pixloc(env, tmp_path, "check-store", STORE, check=False)
    said = out.stdout + out.stderr
    assert out.returncode in (1, 2) and f"s3://maps/{group}" in said and "not JSON" in said, said


def test_a_bad_url_or_storage_options_are_named(s3, env, tmp_path):
    out = pixloc(env, tmp_path, "check-store", "s3://maps/none.zarr", check=False)
    assert out.returncode == 2 and "s3://maps/none.zarr does not exist" in out.stderr
    out = pixloc(env, tmp_path, "check-store", "s3://maps/none.zarr", "--storage-options", "{endpoint", check=False)
    assert out.returncode == 2 and "--storage-options" in out.stderr and "not JSON" in out.stderr
    out = pixloc(env, tmp_path, "check-store", "nosuch://maps/none.zarr", check=False)
    assert out.returncode == 2 and "nosuch://maps/none.zarr" in out.stderr


def test_a_bucket_without_credentials_or_endpoint_is_a_named_error_not_a_traceback(tmp_path):
    """Before: `check-store s3://...` (and `localize`, `build-map`) without credentials, or with an endpoint that
    does not answer, ended in botocore's traceback (NoCredentialsError, EndpointConnectionError: not OSErrors).
    Now the store is named with where its access comes from. No server is needed for either."""
    pytest.importorskip("s3fs")
    import socket
    with socket.socket() as s:  # a port that nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    bare = {k: v for k, v in os.environ.items() if not k.startswith("AWS_") and k != "PIXLOC_STORAGE_OPTIONS"}
    bare.update(AWS_EC2_METADATA_DISABLED="true", AWS_CONFIG_FILE=str(tmp_path / "none"),
                AWS_SHARED_CREDENTIALS_FILE=str(tmp_path / "none"), PYTHONPATH=str(ROOT))
    closed = {**bare, **CREDENTIALS, "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}"}
    for env, error in ((bare, "NoCredentialsError"), (closed, "EndpointConnectionError")):
        out = subprocess.run([sys.executable, "-m", "workflows.cli", "check-store", "s3://nobucket/map.zarr"],
                             capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
        assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-2000:]
        assert f"s3://nobucket/map.zarr: {error}" in out.stderr and "AWS_ACCESS_KEY_ID" in out.stderr
