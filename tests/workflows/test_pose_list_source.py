"""A map source added as a newcomer adds one: ``posetable``, a plain list of ``NAME QW QX QY QZ TX
TY TZ [CAMERA_ID]`` with a COLMAP ``cameras.txt`` beside it, built and localized against with the
commands a user runs (Strecha Herz-Jesus-P8 written as such a list)."""

import subprocess
import sys

import numpy as np
import pytest

from pipeline.evaluate import pose_errors
from pipeline.localization.results import read_records, record_pose
from pipeline.mapping.readers.sources import SOURCES, PoseList, load_queries, map_kinds, posed_images
from pipeline.scene import rotmat_to_qvec
from pipeline.textfiles import InputError

ROOT = __import__("pathlib").Path(__file__).resolve().parents[2]


def write_list(images, folder, one_camera=False):
    folder.mkdir(parents=True, exist_ok=True)
    cams = [images[0].camera] if one_camera else [im.camera for im in images]
    (folder / "cameras.txt").write_text("# CAMERA_ID MODEL WIDTH HEIGHT PARAMS\n" + "".join(
        f"{k + 1} {c.model} {c.width} {c.height} {' '.join(str(float(p)) for p in c.params)}\n"
        for k, c in enumerate(cams)))
    lines = [" ".join([im.name, *(str(float(v)) for v in rotmat_to_qvec(im.cam_from_world[:, :3])),
                       *(str(float(v)) for v in im.cam_from_world[:, 3])] + ([] if one_camera else [str(k + 1)]))
             for k, im in enumerate(images)]
    (folder / "poses.txt").write_text("\n".join(lines) + "\n")
    return folder / "poses.txt"


def test_a_pose_list_with_cameras_is_a_map_and_a_query_source(shared, tmp_path):
    strecha = shared / "data" / "strecha" / "Herz-Jesus-P8"
    images, root = posed_images("strecha", strecha)
    assert SOURCES["posetable"] is PoseList and "posetable" in map_kinds()
    path = write_list(images, tmp_path / "list")
    queries = load_queries("posetable", path, root)
    assert [q.name for q in queries] == [im.name for im in images]
    assert all(np.allclose(q.cam_from_world_gt, im.cam_from_world, atol=1e-5) and q.camera == im.camera
               for q, im in zip(queries, images))
    cli = [sys.executable, "-m", "workflows.cli"]
    held = images[3].name
    built = subprocess.run(cli + ["build-map", "posetable", str(path), "--images", str(root), "--store",
                                  str(tmp_path / "m.zarr"), "--sync", "--resize", "512", "--image-scales", "1",
                                  "--hold-out", held], capture_output=True, text=True, cwd=ROOT)
    assert built.returncode == 0, built.stderr
    run = subprocess.run(cli + ["localize", "posetable", str(path), "--images", str(root), "--store",
                                str(tmp_path / "m.zarr"), "--output", str(tmp_path / "out"), "--sync",
                                "--query-names", held, "--prior", "sift"], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 0, run.stderr
    (record,) = read_records(tmp_path / "out" / "records.jsonl")
    t, R = pose_errors(record_pose(record), images[3].cam_from_world)
    assert record["success"] and t < 0.05 and R < 0.5, (t, R)  # metres: Strecha's poses are metric


def test_a_bad_pose_list_is_named_with_its_line(shared, tmp_path):
    images, root = posed_images("strecha", shared / "data" / "strecha" / "Herz-Jesus-P8")
    path = write_list(images[:3], tmp_path / "one", one_camera=True)
    assert len(posed_images("posetable", path, root)[0]) == 3  # one camera for every image
    (tmp_path / "one" / "cameras.txt").write_text("1 PINHOLE 100 100 50 50 50 50\n2 PINHOLE 100 100 50 50 50 50\n")
    with pytest.raises(InputError, match=r"poses.txt:1: .*holds 2 cameras: give each image's camera id"):
        posed_images("posetable", path, root)
    path.write_text(path.read_text().splitlines()[0] + " 7\n")
    with pytest.raises(InputError, match=r"poses.txt:1: camera 7 is not in"):
        posed_images("posetable", path, root)
    (tmp_path / "one" / "cameras.txt").unlink()
    with pytest.raises(InputError, match="COLMAP cameras file does not exist"):
        posed_images("posetable", path, root)
