"""The rig inputs (``pipeline.rigs``): a rig file (kapture's rigs.txt read as is) and a frames file, every
bad line named by file and line."""

from pathlib import Path

import numpy as np
import pytest

from pipeline.queries import QueryRecord
from pipeline.rigs import read_frames, read_rigs
from pipeline.scene import CameraRecord
from pipeline.textfiles import InputError

CAMERA = CameraRecord("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))


def queries(*names):
    return [QueryRecord(n, Path(n), CAMERA) for n in names]


def test_kapture_rigs_read_as_they_are(shared):
    """virtual_gallery's rigs.txt: six cameras 60 degrees apart, each 0.1 off the rig's centre along its axis."""
    rigs = read_rigs(shared / "data/virtual_gallery/mapping/sensors/rigs.txt")
    cams = rigs["training_rig"]
    assert len(cams) == 6
    np.testing.assert_allclose(cams["training_camera_0"], np.concatenate([np.eye(3), [[0], [0], [-0.1]]], 1))
    for C in cams.values():
        np.testing.assert_allclose(C[:, :3] @ C[:, :3].T, np.eye(3), atol=1e-9)
        np.testing.assert_allclose(C[:, 3], [0, 0, -0.1])
    angles = sorted(np.degrees(np.arccos(np.clip((np.trace(C[:, :3]) - 1) / 2, -1, 1))) for C in cams.values())
    np.testing.assert_allclose(angles, [0, 60, 60, 120, 120, 180], atol=1e-6)


def test_frames_group_images_and_leave_the_others_alone(tmp_path):
    (tmp_path / "rig.txt").write_text("# rig_id sensor_id qw qx qy qz tx ty tz\n"
                                      "car front 1 0 0 0 0 0 0\ncar left, 0.7071068, 0, 0.7071068, 0, 0.2, 0, 0\n")
    rigs = read_rigs(tmp_path / "rig.txt")
    (tmp_path / "frames.txt").write_text("a.jpg car 1 front\nb.jpg car 1 left\nc.jpg car 2 left\n")
    frames = read_frames(tmp_path / "frames.txt", queries("a.jpg", "b.jpg", "c.jpg", "d.jpg"), rigs)
    assert [(f.key, [q.name for q in f.queries]) for f in frames] == [
        ("car/1", ["a.jpg", "b.jpg"]), ("car/2", ["c.jpg"]), ("d.jpg", ["d.jpg"])]
    np.testing.assert_allclose(frames[0].cam_from_body[1][:, 3], [0.2, 0, 0])
    np.testing.assert_allclose(frames[2].cam_from_body[0], np.eye(4)[:3])


@pytest.mark.parametrize("text, message", [
    ("car front 1 0 0 0 0 0\n", "rig.txt:1: expected 'rig_id sensor_id qw qx qy qz tx ty tz' (9 fields), got 8"),
    ("car front 1 0 0 0 0 0 x\n", "rig.txt:1: expected numbers"),
    ("# cams\ncar front 0 0 0 0 0 0 0\n", "rig.txt:2: the quaternion"),
    ("car front 1 0 0 0 0 0 nan\n", "rig.txt:1: non-finite"),
    ("car front 1 0 0 0 0 0 0\ncar front 1 0 0 0 0 0 1\n", "rig.txt:2: camera 'front' of rig 'car' is defined twice"),
    ("# nothing\n", "defines no rig"),
])
def test_a_bad_rig_line_is_named(tmp_path, text, message):
    (tmp_path / "rig.txt").write_text(text)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_rigs(tmp_path / "rig.txt")


@pytest.mark.parametrize("text, message", [
    ("a.jpg car 1\n", "frames.txt:1: expected 'image_name rig_id frame_id sensor_id' (4 fields), got 3"),
    ("x.jpg car 1 front\n", "frames.txt:1: 'x.jpg' is not a query of the list"),
    ("a.jpg bus 1 front\n", "frames.txt:1: rig 'bus' is not in the rig file (it has car)"),
    ("a.jpg car 1 rear\n", "frames.txt:1: camera 'rear' is not a camera of rig 'car' (it has front, left)"),
    ("a.jpg car 1 front\na.jpg car 2 front\n", "frames.txt:2: 'a.jpg' is given twice (first at"),
    ("a.jpg car 1 front\nb.jpg car 1 front\n", "frames.txt:2: frame '1' of rig 'car' has two images of camera 'front'"),
])
def test_a_bad_frames_line_is_named(tmp_path, text, message):
    (tmp_path / "rig.txt").write_text("car front 1 0 0 0 0 0 0\ncar left 1 0 0 0 0 0 0\n")
    (tmp_path / "frames.txt").write_text(text)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_frames(tmp_path / "frames.txt", queries("a.jpg", "b.jpg"), read_rigs(tmp_path / "rig.txt"))


def test_a_sequence_is_cut_into_chunks_in_its_frame_order(tmp_path):
    """Chunks of 2 consecutive lines; each chunk's frame is its first image's camera; a query that no line names
    is alone."""
    from pipeline.rigs import read_odometry
    (tmp_path / "odo.txt").write_text("c.jpg 1 0 0 0 0 0 2\n# a comment\nb.jpg 1 0 0 0 0 0 1\na.jpg 1 0 0 0 0 0 0\n")
    frames = read_odometry(tmp_path / "odo.txt", queries("a.jpg", "b.jpg", "c.jpg", "d.jpg"), 2)
    assert [[q.name for q in f.queries] for f in frames] == [["c.jpg", "b.jpg"], ["a.jpg"], ["d.jpg"]]
    np.testing.assert_allclose(frames[0].cam_from_body[0], np.eye(4)[:3], atol=1e-12)
    np.testing.assert_allclose(frames[0].cam_from_body[1][:, 3], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(frames[1].cam_from_body[0], np.eye(4)[:3], atol=1e-12)


@pytest.mark.parametrize("text, message", [
    ("a.jpg 1 0 0 0 0 0\n", "odo.txt:1: expected 'name qw qx qy qz tx ty tz' (8 fields), got 7"),
    ("a.jpg 1 0 0 0 0 0 0\nb.jpg 0 0 0 0 0 0 0\n", "odo.txt:2: the quaternion"),
    ("a.jpg 1 0 0 0 0 0 0\na.jpg 1 0 0 0 0 0 1\n", "odo.txt:2: 'a.jpg' is given twice (first at"),
    ("x.jpg 1 0 0 0 0 0 0\n", "odo.txt:1: 'x.jpg' is not a query of the list"),
])
def test_a_bad_odometry_line_is_named(tmp_path, text, message):
    from pipeline.rigs import read_odometry
    (tmp_path / "odo.txt").write_text(text)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_odometry(tmp_path / "odo.txt", queries("a.jpg", "b.jpg"), 5)
