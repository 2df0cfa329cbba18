"""Fault catalogue, class 1: inputs. Every image, list, camera and name goes through one reader
(``pipeline.images.read_image_for``, ``pipeline.scene.CameraRecord.check``,
``pipeline.scene.name_problem``): a bad one is that item's failure, named, never a crash of the
run and never a wrong success."""

import struct
import time
import zlib

import numpy as np
import pytest
from PIL import Image

from pipeline.mapping.build import build_map
from pipeline.store.feature_groups import feature_key
from pipeline.mapping.features import FeatureConfig
from pipeline.images import ImageReadError, read_image
from pipeline.localization.results import pose_name
from pipeline.scene import CameraRecord, ImageRecord
from pipeline.store.layout import open_store
from workflows.localize import plan_localization, run_sync
from pipeline.mapping.readers.sources import load_queries

from .conftest import pixloc


def _bomb_png(path, side=30000):
    """A small PNG that declares side x side RGB pixels (its data is a few rows of zeros)."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    rows = zlib.compress(b"\0" * (1 + 3 * side) * 8, 9)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", rows) + chunk(b"IEND", b""))
    return path


# --- image files ---------------------------------------------------------------------------

def test_zero_byte_query_fails_that_query_and_the_run_goes_on(stairs, tmp_path):
    """Before: cv2.error aborted the whole run (and Dask cancelled every other shard)."""
    (tmp_path / "empty.jpg").write_bytes(b"")
    bad = stairs.queries[0].__class__(**{**stairs.queries[0].__dict__, "path": tmp_path / "empty.jpg"})
    records = run_sync(plan_localization(stairs.job, [bad, stairs.queries[1]], tmp_path / "out"))
    assert not records[0]["success"] and "empty.jpg" in records[0]["reason"] and "0 bytes" in records[0]["reason"]
    assert records[1]["references"]  # the other query ran


def test_zero_byte_map_image_is_that_image_failure(shared, tmp_path):
    """Before: build-map stopped at that image on every rerun: the map could never be built."""
    import shutil

    from pipeline.mapping.readers.colmap import read_colmap
    root = shared / "data" / "maupertuis"
    shutil.copytree(root / "images", tmp_path / "images")
    scene = read_colmap(root / "reconstruction", tmp_path / "images")
    scene.images[2].path.write_bytes(b"")
    results = build_map(scene, tmp_path / "m.zarr", FeatureConfig(resize=256, image_scales=(1,)))
    assert [r.status for r in results] == ["done", "done", "failed", "done"]
    assert "0 bytes" in results[2].reason


def test_decompression_bomb_is_refused_from_its_header(tmp_path, monkeypatch):
    """Before: a 30000x30000 PNG was decoded in full (5.6 GB RSS, 30 s) or died of memory."""
    bomb = _bomb_png(tmp_path / "bomb.png")
    assert bomb.stat().st_size < 200_000
    t0 = time.perf_counter()
    with pytest.raises(ImageReadError, match=r"bomb.png declares 30000x30000 = 900,000,000 pixels.*limit"):
        read_image(bomb)
    assert time.perf_counter() - t0 < 2.0
    monkeypatch.setenv("PIXLOC_MAX_IMAGE_PIXELS", "1000")  # the limit is documented and can be set
    small = tmp_path / "small.png"
    Image.new("RGB", (40, 30)).save(small)
    with pytest.raises(ImageReadError, match="1,200 pixels"):
        read_image(small)


def test_decompression_bomb_query_fails_alone(stairs, tmp_path):
    bomb = _bomb_png(tmp_path / "bomb.png")
    q = stairs.queries[0]
    bad = q.__class__(**{**q.__dict__, "path": bomb})
    records = run_sync(plan_localization(stairs.job, [bad, stairs.queries[1]], tmp_path / "out"))
    assert not records[0]["success"] and "limit" in records[0]["reason"]
    assert records[1]["references"]


def test_pixloc_queries_skips_a_bomb_and_a_truncated_jpeg_and_lists_the_rest(shared, tmp_path):
    """Before: PIL's DecompressionBombError killed `pixloc queries` (no list written), and a
    JPEG cut to 5,000 bytes was listed."""
    folder = tmp_path / "photos"
    folder.mkdir()
    _bomb_png(folder / "bomb.png")
    good = shared / "data" / "sacre_coeur" / "mapping"
    good = sorted(good.iterdir())[0]
    (folder / "good.jpg").write_bytes(good.read_bytes())
    (folder / "cut.jpg").write_bytes(good.read_bytes()[:5000])
    out = pixloc("queries", folder, "--out", tmp_path / "list.txt")
    assert out.returncode == 1, out.stderr
    listed = [line.split()[0] for line in (tmp_path / "list.txt").read_text().splitlines() if not line.startswith("#")]
    assert listed == ["good.jpg"]
    assert "skipped bomb.png" in out.stdout and "limit" in out.stdout
    assert "skipped cut.jpg" in out.stdout


# --- map images against their camera ------------------------------------------------------

def _valid_fraction(store, conf, index) -> float:
    root = open_store(store)
    start, n = int(root["images/row_start"][index]), int(root["images/num_obs"][index])
    return float(root[f"features/{feature_key(conf)}/s0/valid"][start:start + n, 0].mean())


@pytest.mark.parametrize("change", ["half size", "exif orientation 6", "other aspect ratio"])
def test_map_image_that_does_not_match_its_camera(shared, tmp_path, change):
    """Before: a map image shrunk to half size or tagged EXIF orientation 6 was extracted silently
    with 9 % / 67 % valid observations instead of 98 %. Now map images follow the queries' rule:
    the same aspect ratio is rescaled, pixels as stored are used where the tag swapped the sides,
    and another aspect ratio is that image's failure."""
    import shutil

    from pipeline.mapping.readers.colmap import read_colmap
    root = shared / "data" / "maupertuis"
    conf = FeatureConfig(resize=256, image_scales=(1,))
    shutil.copytree(root / "images", tmp_path / "images")
    scene = read_colmap(root / "reconstruction", tmp_path / "images")
    build_map(scene, tmp_path / "ref.zarr", conf)
    victim = scene.images[1].path
    image = Image.open(victim)
    if change == "half size":
        image.resize((image.width // 2, image.height // 2)).save(victim, quality=95)
    elif change == "exif orientation 6":
        exif = image.getexif()
        exif[274] = 6
        image.save(victim, quality=95, exif=exif)
    else:
        image.crop((0, 0, image.width, image.height // 2)).save(victim, quality=95)
    results = build_map(scene, tmp_path / "m.zarr", conf)
    if change == "other aspect ratio":
        assert results[1].status == "failed" and "another aspect ratio" in results[1].reason
        return
    assert results[1].status == "done"
    expected = _valid_fraction(tmp_path / "ref.zarr", conf, 1)
    assert expected > 0.9
    assert _valid_fraction(tmp_path / "m.zarr", conf, 1) == pytest.approx(expected, abs=0.03)


# --- cameras -------------------------------------------------------------------------------

@pytest.mark.parametrize("focal", ["-525", "0", "1e-30"])
def test_degenerate_focal_length_fails_the_query_at_read(stairs, tmp_path, focal):
    """Before: PINHOLE with f = -525, 0 or 1e-30 was localized, and reported a success with --no-verify."""
    q = stairs.queries[0]
    (tmp_path / "list.txt").write_text(f"{q.name} PINHOLE 640 480 {focal} {focal} 320 240\n")
    listed = load_queries("list", tmp_path / "list.txt", stairs.root)
    records = run_sync(plan_localization(stairs.unverified(), listed, tmp_path / "out"))
    assert not records[0]["success"] and "list.txt:1" in records[0]["reason"]
    assert "focal length" in records[0]["reason"]


def test_every_camera_is_checked_where_it_is_read():
    ok = CameraRecord("PINHOLE", 640, 480, (525.0, 525.0, 320.0, 240.0))
    assert ok.check() is None
    for bad, words in [(CameraRecord("PINHOLE", 640, 480, (525.0, 525.0, 3200.0, 240.0)), "principal point"),
                       (CameraRecord("PINHOLE", 640, 0, (525.0, 525.0, 320.0, 240.0)), "invalid size"),
                       (CameraRecord("SIMPLE_RADIAL", 640, 480, (-1.0, 320.0, 240.0, 0.0)), "focal length"),
                       (CameraRecord("PINHOLE", 640, 480, (525.0, float("inf"), 320.0, 240.0)), "non-finite"),
                       (CameraRecord("PINHOLE", 640, 480, (525.0, 320.0, 240.0)), "parameters")]:
        assert words in bad.check()
        image = ImageRecord("a.jpg", None, bad, np.eye(3, 4))
        assert words in image.check()  # map images: the same check, at the structure stage


# --- names ---------------------------------------------------------------------------------

def test_names_are_relative_paths_inside_their_folder(stairs, tmp_path):
    """Before: a name with a space failed as 'invalid literal for int()'; '../../outside.jpg' and
    absolute names were read from outside --query-images and written to poses.txt."""
    images = tmp_path / "a" / "b"
    images.mkdir(parents=True)
    q = stairs.queries[0]
    (tmp_path / "outside.jpg").write_bytes(q.path.read_bytes())
    cam = "PINHOLE 640 480 525 525 320 240"
    (tmp_path / "list.txt").write_text(
        f"my photo.jpg {cam}\n../../outside.jpg {cam}\n{tmp_path / 'outside.jpg'} {cam}\n")
    listed = load_queries("list", tmp_path / "list.txt", images)
    reasons = [x.error for x in listed]
    assert "name has spaces ('my photo.jpg')" in reasons[0]
    assert "leaves the image folder" in reasons[1] and "list.txt:2" in reasons[1]
    assert "is absolute" in reasons[2]
    records = run_sync(plan_localization(stairs.job, listed, tmp_path / "out"))
    assert not any(r["success"] or r["references"] for r in records)
    assert (tmp_path / "out" / "poses.txt").read_text() == ""
    assert "leaves the image folder" in ImageRecord("../x.jpg", None, q.camera, np.eye(3, 4)).check()


def test_camera_pose_names_never_start_with_a_slash():
    """Before: --pose-names camera wrote '/a.jpg' for a query without a folder."""
    assert pose_name("a.jpg", "camera") == "a.jpg"
    assert pose_name("seq-01/a.jpg", "camera") == "seq-01/a.jpg"
    assert pose_name("x/seq-01/a.jpg", "camera") == "seq-01/a.jpg"


@pytest.mark.parametrize("case", ["par_line", "par_number", "bundle_short", "bundle_images", "llff_shape",
                                  "llff_count", "opensfm_json", "transforms_matrix", "transforms_image"])
def test_a_damaged_posed_format_names_its_file_and_what_is_wrong(shared, tmp_path, case):
    """The map formats' readers (LLFF, Middlebury, Bundler, OpenSfM, transforms.json) refuse a damaged
    file with a SceneError that names it (and the line, where there are lines), never a raw error."""
    import json

    from pipeline.mapping.readers.bundler import read_bundler
    from pipeline.mapping.readers.llff import read_llff
    from pipeline.mapping.readers.middlebury import read_middlebury
    from pipeline.mapping.readers.opensfm import read_opensfm
    from pipeline.mapping.readers.transforms import read_transforms
    from pipeline.scene import SceneError
    from pipeline.textfiles import InputError
    data = shared / "data"
    if case.startswith("par"):
        src = data / "middlebury" / "templeRing"
        for f in src.iterdir():
            (tmp_path / f.name).symlink_to(f)
        par = tmp_path / "templeR_par.txt"
        par.unlink()
        lines = (src / "templeR_par.txt").read_text().splitlines()
        lines[3] = lines[3].rsplit(" ", 1)[0] if case == "par_line" else lines[3].replace("1520.4", "x1520")
        par.write_text("\n".join(lines))
        with pytest.raises(SceneError, match=rf"{par}:4: " + ("expected an image name and 21 numbers"
                                                             if case == "par_line" else "a value is not a number")):
            read_middlebury(tmp_path)
    elif case.startswith("bundle"):
        bundle = tmp_path / "bundle.out"
        text = (data / "bundler_kermit" / "results.example" / "bundle.out").read_text().splitlines()
        bundle.write_text("\n".join(text[:9]) if case == "bundle_short" else "\n".join(text))
        images = data / "bundler_kermit" if case == "bundle_short" else tmp_path
        match = "camera 1 is cut short" if case == "bundle_short" else "11 cameras but 1 images"
        if case == "bundle_images":
            (tmp_path / "one.jpg").write_bytes((data / "bundler_kermit" / "kermit000.jpg").read_bytes())
        with pytest.raises(SceneError, match=rf"{bundle}.*{match}"):
            read_bundler(bundle, images)
    elif case.startswith("llff"):
        (tmp_path / "images").mkdir()
        for name in sorted((data / "beer_capture" / "images").iterdir())[:3]:
            (tmp_path / "images" / name.name).symlink_to(name)
        poses = np.load(data / "beer_capture" / "poses_bounds.npy")
        np.save(tmp_path / "poses_bounds.npy", poses[:3, :15] if case == "llff_shape" else poses[:4])
        with pytest.raises(SceneError, match=rf"{tmp_path / 'poses_bounds.npy'}: " +
                           (r"expected N x 17" if case == "llff_shape" else r"4 poses for 3 images")):
            read_llff(tmp_path)
    elif case == "opensfm_json":
        path = tmp_path / "reconstruction.json"
        path.write_text((data / "opensfm_berlin" / "reconstruction_example.json").read_text()[:5000])
        with pytest.raises(InputError, match=rf"{path}:\d+: OpenSfM reconstruction is not valid JSON"):
            read_opensfm(path, data / "opensfm_berlin" / "images")
    else:
        path = tmp_path / "transforms.json"
        frame = {"file_path": "missing.jpg" if case == "transforms_image" else "a.jpg",
                 "transform_matrix": [[1, 0, 0, 0]] * 3, "fl_x": 500, "w": 640, "h": 480}
        (tmp_path / "a.jpg").write_bytes((data / "bundler_kermit" / "kermit000.jpg").read_bytes())
        path.write_text(json.dumps({"frames": [frame]}))
        what = "transform_matrix is not a finite 4x4" if case == "transforms_matrix" else "image .* does not exist"
        with pytest.raises(SceneError, match=rf"{path}: frame 0: {what}"):
            read_transforms(path)
