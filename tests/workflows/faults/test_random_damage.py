"""Fault catalogue, the property behind every class: random damage to each reader's input, and to
any file of a store, gives a clear error naming the file (and line), or a correct result; never a
traceback of another kind, never a wrong success."""

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.images import ImageReadError, read_image_for
from pipeline.queries import QueryRecord, read_queries_with_intrinsics
from pipeline.localization.results import read_records
from pipeline.scene import CameraRecord, ImageRecord, name_problem
from pipeline.store.layout import StoreError
from pipeline.store.check import check_store
from pipeline.textfiles import InputError, read_pairs, read_poses
from workflows.localize import stored_job

ODD = ["nan", "inf", "-inf", "-1", "0", "1e999", "x", "", "../a.jpg", "/abs.jpg", "a b", "\u00e9", "0x10", "-0"]
SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@st.composite
def damaged(draw, text: str) -> bytes:
    """``text`` after one to three kinds of damage: truncation, byte flips, a field replaced,
    dropped or added, a line repeated."""
    data = text.encode()
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["truncate", "flip", "field", "drop", "add", "repeat"]))
        lines = data.split(b"\n")
        k = draw(st.integers(0, max(len(lines) - 1, 0)))
        fields = lines[k].split(b" ")
        j = draw(st.integers(0, max(len(fields) - 1, 0)))
        if kind == "truncate":
            data = data[:draw(st.integers(0, len(data)))]
            continue
        if kind == "flip" and data:
            i = draw(st.integers(0, len(data) - 1))
            data = data[:i] + bytes([draw(st.integers(0, 255))]) + data[i + 1:]
            continue
        if kind == "field":
            fields[j] = draw(st.sampled_from(ODD)).encode()
        elif kind == "drop" and len(fields) > 1:
            del fields[j]
        elif kind == "add":
            fields.insert(j, draw(st.sampled_from(ODD)).encode())
        elif kind == "repeat":
            lines.insert(k, lines[k])
        if kind != "repeat":
            lines[k] = b" ".join(fields)
        data = b"\n".join(lines)
    return data


def _write(data: bytes, name: str) -> Path:
    path = Path(tempfile.mkdtemp()) / name
    path.write_bytes(data)
    return path


def _read(reader, data: bytes, name: str, errors=InputError):
    """``reader(path)`` of ``data`` written to a file ``name``: its result, or None when it refused
    the file with an error that starts with the file's path (and line)."""
    path = _write(data, name)
    try:
        return reader(path)
    except errors as e:
        assert str(e).startswith(f"{path}:") or str(path.parent) in str(e), str(e)
        return None


POSES = ("seq-01/frame-000000.color.jpg 0.9 0.1 0.2 0.3 1.5 -0.2 3\n"
         "seq-01/frame-000001.color.jpg 1 0 0 0 0 0 0\n# a comment\n"
         "seq-04/frame-000000.color.jpg 0.5 0.5 0.5 0.5 -1 2 0.25\n")


@settings(max_examples=150, **SETTINGS)
@given(damaged(POSES))
def test_poses_file(data):
    table = _read(read_poses, data, "poses.txt")
    for name, T in (table.poses.items() if table else []):  # what was read is a pose, by its whole name
        assert T.shape == (3, 4) and np.isfinite(T).all()
        np.testing.assert_allclose(T[:, :3] @ T[:, :3].T, np.eye(3), atol=1e-6)
        assert table.find(name) is T


@settings(max_examples=100, **SETTINGS)
@given(damaged("q1.jpg db1.jpg\nq1.jpg db2.jpg\nq2.jpg db1.jpg\n"))
def test_pairs_file(data):
    pairs = _read(read_pairs, data, "pairs.txt") or {}
    assert all(isinstance(q, str) and refs and all(isinstance(r, str) for r in refs) for q, refs in pairs.items())


@settings(max_examples=150, **SETTINGS)
@given(damaged("a.jpg PINHOLE 640 480 525 525 320 240\nsub/b.jpg SIMPLE_RADIAL 1024 768 800 512 384 0.01\n"
               "c.jpg OPENCV 640 480 500 500 320 240 0.1 0.01 0 0\n"))
def test_query_list(data):
    path, queries = _read(lambda p: (p, read_queries_with_intrinsics(p, p.parent)), data, "list.txt") or (None, [])
    for q in queries:  # each query fails with its line, or is a usable query inside its folder
        if q.error:
            assert q.error.startswith(f"{path}:")
        else:
            assert q.camera.check() is None and name_problem(q.name) is None


JOB = json.dumps({"job": {"store": "/x/map.zarr", "prior": "top1"}, "queries": ["a.jpg", "b.jpg"], "shard_size": 8})


@settings(max_examples=100, **SETTINGS)
@given(damaged(JOB))
def test_job_file(data):
    job = _read(lambda p: stored_job(p.parent), data, "job.json", ValueError)  # or a folder not ours
    assert job is None or (isinstance(job["job"], dict) and isinstance(job["queries"], list)
                           and isinstance(job["shard_size"], int))


@settings(max_examples=100, **SETTINGS)
@given(damaged(json.dumps({"name": "a.jpg", "success": True}) + "\n" + json.dumps({"name": "b", "x": [1]}) + "\n"))
def test_records_file(data):
    records = _read(read_records, data, "shard-00000.jsonl") or []
    assert all(isinstance(r, dict) and "name" in r for r in records)


@pytest.fixture(scope="module")
def image_bytes(shared):
    jpeg = (shared / "data" / "7scenes_stairs" / "seq-01" / "frame-000000.color.jpg").read_bytes()
    png = sorted((shared / "data" / "middlebury").rglob("*.png"))[0].read_bytes()
    return {"jpg": jpeg, "png": png}


@settings(max_examples=60, **SETTINGS)
@given(kind=st.sampled_from(["jpg", "png"]), cut=st.floats(0, 1), flips=st.lists(st.tuples(st.floats(0, 1),
       st.integers(0, 255)), max_size=4))
def test_image_file(image_bytes, kind, cut, flips):
    data = bytearray(image_bytes[kind])
    for where, value in flips:
        data[int(where * (len(data) - 1))] = value
    if cut < 0.5:
        data = data[:int(cut * 2 * len(data))]
    path = _write(bytes(data), f"image.{kind}")
    camera = CameraRecord("PINHOLE", 640, 480, (525.0, 525.0, 320.0, 240.0))
    try:
        rgb, cam, _ = read_image_for(path, camera)
    except ImageReadError as e:
        assert str(path) in str(e)
        return
    assert rgb.shape == (cam.height, cam.width, 3) and cam.check() is None


@settings(max_examples=25, **SETTINGS)
@given(choice=st.floats(0, 1), damage=st.sampled_from(["delete", "truncate", "flip", "folder"]), at=st.floats(0, 1))
def test_store_file(stairs, choice, damage, at):
    """Any chunk or shard file of a store, deleted, cut, flipped or replaced by a folder, is found
    by check-store (or refused when the store is opened), naming the store."""
    work = Path(tempfile.mkdtemp())
    store = work / "map.zarr"
    shutil.copytree(stairs.job.store, store)
    files = sorted(p for p in store.rglob("*") if p.is_file() and "/c/" in p.as_posix() or p.parent.name == "c"
                   and p.is_file())
    victim = files[int(choice * (len(files) - 1))]
    data = victim.read_bytes()
    if damage == "delete":
        victim.unlink()
    elif damage == "truncate":
        victim.write_bytes(data[:int(at * (len(data) - 1))])
    elif damage == "flip":
        i = int(at * (len(data) - 1))
        victim.write_bytes(data[:i] + bytes([data[i] ^ 0x5A]) + data[i + 1:])
    else:
        victim.unlink()
        victim.mkdir()
    try:
        report = check_store(store)
    except StoreError as e:
        assert str(store) in str(e)
        return
    finally:
        pass
    assert not report.ok, f"{damage} of {victim.relative_to(store)} was not found"
    shutil.rmtree(work)


# --- the dataset readers: kapture, Strecha, 7-Scenes and pose.txt trajectories -------------------

def _named_or_checked(read, path: Path, folder: bool = False):
    """``read()`` gives images that are usable or refused with a reason where they are checked, or
    refuses with an error naming ``path`` (with ``folder``: a file of its folder, where the damage
    shows in another file that refers to it); never another exception."""
    from pipeline.scene import SceneError
    try:
        images = read()
    except (SceneError, InputError) as e:
        assert str(path.parent if folder else path) in str(e), str(e)
        return
    for im in images:
        reason = im.check()
        assert reason is None or isinstance(reason, str)


@pytest.fixture(scope="module")
def kapture_text(shared):
    folder = shared / "data" / "virtual_gallery" / "mapping" / "sensors"
    return {p.name: p.read_text() for p in folder.glob("*.txt")}


@settings(max_examples=80, **SETTINGS)
@given(data=st.data(), which=st.sampled_from(["sensors.txt", "trajectories.txt", "records_camera.txt", "rigs.txt"]))
def test_kapture_files(kapture_text, data, which):
    from pipeline.mapping.readers.kapture import read_kapture
    root = Path(tempfile.mkdtemp())
    (root / "sensors").mkdir()
    for name, text in kapture_text.items():
        (root / "sensors" / name).write_text(text)
    path = root / "sensors" / which
    path.write_bytes(data.draw(damaged(kapture_text[which].replace(", ", " ")).map(
        lambda b: b.replace(b" ", b", "))))
    _named_or_checked(lambda: read_kapture(root), path, folder=True)


@settings(max_examples=60, **SETTINGS)
@given(damaged("1 0 0\n0 1 0\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n640 480\n"))
def test_strecha_camera_file(data):
    from pipeline.mapping.readers.strecha import read_strecha_camera
    path = _write(data, "0000.jpg.camera")
    _named_or_checked(lambda: [ImageRecord("0000.jpg", path, *read_strecha_camera(path))], path)


@settings(max_examples=60, **SETTINGS)
@given(damaged("9.9e-01 -1.3e-02 -1.5e-01 1.6e-01\n-3.7e-02 9.4e-01 -3.2e-01 8.9e-01\n"
               "1.5e-01 3.2e-01 9.3e-01 6.2e-01\n0 0 0 1\n"))
def test_seven_scenes_pose_file(data):
    from pipeline.mapping.readers.rgbd import read_7scenes
    root = Path(tempfile.mkdtemp())
    (root / "seq-01").mkdir()
    (root / "seq-01" / "frame-000000.color.jpg").write_bytes(b"")  # the reader reads no pixels
    path = root / "seq-01" / "frame-000000.pose.txt"
    path.write_bytes(data)
    _named_or_checked(lambda: read_7scenes(root, [1]), path)


@settings(max_examples=60, **SETTINGS)
@given(damaged("0.1 0.2 0.3 0 0 0 1\n-0.5 0.2 1.5 0.1 0.2 0.3 0.9\n"))
def test_pose_txt_trajectory(data):
    from pipeline.mapping.readers.rgbd import read_pose_txt
    root = Path(tempfile.mkdtemp())
    (root / "pose.txt").write_bytes(data)
    camera = CameraRecord("PINHOLE", 640, 480, (518.0, 519.0, 325.5, 253.5))
    _named_or_checked(lambda: read_pose_txt(root, camera, 1e-3), root / "pose.txt")


RIG = "car front 1 0 0 0 0 0 0\ncar, left, 0.7071068, 0, 0.7071068, 0, 0.2, 0, 0\n# cams\nbus rear 0 0 1 0 0 0 -1\n"
RIG_QUERIES = ["a.jpg", "b.jpg", "c.jpg", "d.jpg"]


def _rig_queries():
    return [QueryRecord(n, Path(n), CameraRecord("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0)))
            for n in RIG_QUERIES]


def _rotation_ok(T):
    return T.shape == (3, 4) and np.isfinite(T).all() and np.allclose(T[:, :3] @ T[:, :3].T, np.eye(3), atol=1e-6)


@settings(max_examples=120, **SETTINGS)
@given(damaged(RIG))
def test_rig_file(data):
    from pipeline.rigs import read_rigs
    rigs = _read(read_rigs, data, "rigs.txt") or {}
    assert all(_rotation_ok(C) for cams in rigs.values() for C in cams.values())


@settings(max_examples=120, **SETTINGS)
@given(damaged("a.jpg car 1 front\nb.jpg car 1 left\nc.jpg bus 7 rear\n"))
def test_rig_frames_file(data):
    """Every query is in exactly one frame (a body or alone), each frame's cameras are the rig file's."""
    from pipeline.rigs import read_frames, read_rigs
    rigs = read_rigs(_write(RIG.encode(), "rigs.txt"))
    frames = _read(lambda p: read_frames(p, _rig_queries(), rigs), data, "frames.txt")
    if frames is not None:
        names = [q.name for f in frames for q in f.queries]
        assert sorted(names) == sorted(RIG_QUERIES)
        known = [C for cams in rigs.values() for C in cams.values()] + [np.eye(4)[:3]]
        assert all(any(np.array_equal(C, K) for K in known) for f in frames for C in f.cam_from_body)


@settings(max_examples=120, **SETTINGS)
@given(damaged("a.jpg 1 0 0 0 0 0 0\nb.jpg 1 0 0 0 0.1 0 0\nc.jpg 0.9 0.1 0 0 0.2 0 0\n"), st.integers(1, 4))
def test_odometry_file(data, chunk):
    """Every query is in exactly one chunk or alone; a chunk's first camera is its frame."""
    from pipeline.rigs import read_odometry
    frames = _read(lambda p: read_odometry(p, _rig_queries(), chunk), data, "odometry.txt")
    if frames is not None:
        assert sorted(q.name for f in frames for q in f.queries) == sorted(RIG_QUERIES)
        for f in frames:
            assert len(f.queries) <= chunk and all(_rotation_ok(C) for C in f.cam_from_body)
            np.testing.assert_allclose(f.cam_from_body[0], np.eye(4)[:3], atol=1e-9)
