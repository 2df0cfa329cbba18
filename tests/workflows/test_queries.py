"""``pixloc queries``: intrinsics of uncalibrated photos from EXIF, on a real photo and made-up files."""

import shutil

import numpy as np
import pytest
from PIL import Image

from pipeline.exif import exif_camera
from pipeline.images import read_image
from pipeline.queries import read_queries_with_intrinsics
from workflows.cli import main as pixloc


def _jpeg(path, size, focal_mm=None, plane_res=None, unit=None, orientation=None):
    exif = Image.Exif()
    sub = exif.get_ifd(0x8769)
    if focal_mm:
        sub[37386] = focal_mm
    if plane_res:
        sub[41486], sub[41488] = plane_res, unit
    if orientation:
        exif[274] = orientation
    Image.fromarray(np.full((size[1], size[0], 3), 128, np.uint8)).save(path, exif=exif)
    return path


def test_35mm_equivalent_focal_of_a_real_photo(shared):
    """The Sacre Coeur night photo (Panasonic DMC-TZ2) says 34 mm in 35 mm film: 34 / 35 x 2816 px."""
    cam = exif_camera(shared / "data" / "sacre_coeur" / "query" / "night.jpg")
    assert cam.source == "35mm-equivalent" and cam.camera.model == "SIMPLE_PINHOLE"
    assert (cam.camera.width, cam.camera.height) == (2816, 2112)
    assert cam.camera.params == pytest.approx((34 / 35 * 2816, 1408, 1056))


def test_focal_plane_resolution_and_orientation(tmp_path):
    # 4.5 mm lens, 2000 px per cm of sensor: 900 px; orientation 6 decodes as a portrait image
    path = _jpeg(tmp_path / "a.jpg", (400, 300), focal_mm=4.5, plane_res=2000.0, unit=3, orientation=6)
    cam = exif_camera(path)
    assert cam.source == "focal-plane" and cam.camera.params == pytest.approx((900.0, 150.0, 200.0))
    assert read_image(path).shape[:2] == (cam.camera.height, cam.camera.width) == (400, 300)


def test_the_command_writes_a_list_that_localize_reads(shared, tmp_path, capsys):
    photos = tmp_path / "photos"
    (photos / "night").mkdir(parents=True)
    shutil.copy(shared / "data" / "sacre_coeur" / "query" / "night.jpg", photos / "night" / "n.jpg")
    mapping = sorted((shared / "data" / "sacre_coeur" / "mapping").glob("*.jpg"))[0]
    shutil.copy(mapping, photos / "plain.jpg")  # no EXIF at all
    _jpeg(photos / "fp.jpg", (400, 300), focal_mm=4.5, plane_res=2000.0, unit=3)
    (photos / "broken.jpg").write_bytes(b"not a jpeg")
    out = tmp_path / "queries_with_intrinsics.txt"
    assert pixloc(["queries", str(photos), "--out", str(out)]) == 1  # one image skipped
    text = capsys.readouterr().out
    assert "3 of 4 images" in text and "skipped broken.jpg: " in text
    assert "1 without EXIF focal length: 1.2 x the larger image side" in text
    queries = {q.name: q for q in read_queries_with_intrinsics(out, photos)}
    assert sorted(queries) == ["fp.jpg", "night/n.jpg", "plain.jpg"]
    assert all(q.error is None for q in queries.values())
    w, h = Image.open(mapping).size
    assert queries["plain.jpg"].camera.params == pytest.approx((1.2 * max(w, h), w / 2, h / 2), abs=1e-3)
    assert queries["night/n.jpg"].camera.params[0] == pytest.approx(34 / 35 * 2816, abs=0.01)
    assert queries["fp.jpg"].camera.params[0] == pytest.approx(900.0)
    # another default for images without EXIF
    assert pixloc(["queries", str(photos / "plain.jpg"), "--out", str(out), "--default-focal", "0.8"]) == 0
    assert read_queries_with_intrinsics(out, photos)[0].camera.params[0] == pytest.approx(0.8 * max(w, h), abs=1e-3)


def test_a_query_list_that_is_a_folder_or_absent_is_named_as_such(tmp_path):
    """Before: a folder given as the query list was 'Query list ... does not exist'."""
    with pytest.raises(ValueError, match=r"query list does not exist \(it is a folder\)"):
        read_queries_with_intrinsics(tmp_path, tmp_path)
    with pytest.raises(ValueError, match=r"nothere\.txt: query list does not exist$"):
        read_queries_with_intrinsics(tmp_path / "nothere.txt", tmp_path)
