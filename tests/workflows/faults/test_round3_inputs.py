"""Fault catalogue, round three, the formats users bring and settings from outside the command line:
a duplicate is refused by every reader with where it was found (COLMAP's database aborts the
process on one); a byte-order mark is not data; every camera model a format can declare is honoured
or refused; counts a file declares are checked; settings from the environment are checked as
their flags are; a default builds every map a user can hand over."""

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from pipeline.scene import SceneError
from pipeline.textfiles import InputError
from pipeline.mapping.readers.sources import posed_images

from .conftest import pixloc

BOM = "\ufeff"


def _links(root: Path, files) -> None:
    for f in files:
        (root / f.name).symlink_to(f)


def _transforms(shared, tmp_path, frames=None, **top) -> Path:
    """A transforms.json of two kermit photos (a camera 1 m apart), ``top`` at its top level."""
    kermit = shared / "data" / "bundler_kermit"
    tmp_path.mkdir(parents=True, exist_ok=True)
    _links(tmp_path, [kermit / "kermit000.jpg", kermit / "kermit001.jpg"])
    pose = np.eye(4).tolist()
    moved = np.eye(4)
    moved[0, 3] = 1
    frames = frames or [{"file_path": "kermit000.jpg", "transform_matrix": pose},
                        {"file_path": "kermit001.jpg", "transform_matrix": moved.tolist()}]
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"fl_x": 500, "w": 640, "h": 480, **top, "frames": frames}))
    return path


def _middlebury(shared, tmp_path, edit=None) -> Path:
    temple = shared / "data" / "middlebury" / "templeRing"
    par = next(temple.glob("*_par.txt"))
    _links(tmp_path, sorted(temple.glob("*.png")))
    lines = par.read_text().splitlines()
    (tmp_path / par.name).write_text("\n".join(edit(lines) if edit else lines) + "\n")
    return tmp_path / par.name


def _first_present(shared, lines):
    temple = shared / "data" / "middlebury" / "templeRing"
    return next(k for k, line in enumerate(lines[1:], 1) if (temple / line.split()[0]).is_file())


# -- duplicates: every reader, named where found -------------------------------------------------

def test_a_duplicate_frame_of_transforms_json_is_named(shared, tmp_path):
    """Before: SQLite error: constraint failed, SIGABRT (rc 134) and a C++ stack dump."""
    frame = {"file_path": "kermit000.jpg", "transform_matrix": np.eye(4).tolist()}
    path = _transforms(shared, tmp_path, [frame, {**frame}])
    with pytest.raises(SceneError, match=r"frame 1: image kermit000.jpg is listed twice \(first at .*frame 0\)"):
        posed_images("transforms", path)


def test_a_repeated_middlebury_line_is_named_with_its_line(shared, tmp_path):
    def repeat(lines):
        k = _first_present(shared, lines)
        return [str(int(lines[0]) + 1)] + lines[1:] + [lines[k]]
    par = _middlebury(shared, tmp_path, repeat)
    n = len(par.read_text().splitlines())
    with pytest.raises(SceneError, match=rf"{par}:{n}: image .* is listed twice \(first at {par}:\d+\)"):
        posed_images("middlebury", tmp_path)


def test_duplicates_in_kapture_are_named(shared, tmp_path):
    src = shared / "data" / "virtual_gallery" / "mapping"
    shutil.copytree(src, tmp_path / "k", symlinks=True)
    sensors = tmp_path / "k" / "sensors"
    for name in ("records_camera.txt", "trajectories.txt", "sensors.txt"):
        original = (sensors / name).read_text()
        data = [line for line in original.splitlines() if line.strip() and not line.startswith("#")]
        (sensors / name).write_text(original + data[-1] + "\n")
        with pytest.raises(SceneError, match=rf"{sensors / name}:\d+: .*twice"):
            posed_images("kapture", tmp_path / "k")
        (sensors / name).write_text(original)


def test_a_duplicate_key_in_an_opensfm_reconstruction_is_named(shared, tmp_path):
    src = shared / "data" / "opensfm_berlin"
    text = (src / "reconstruction_example.json").read_text()
    model = json.loads(text)
    shot = sorted(model[0]["shots"])[0]
    body = json.dumps(model[0]["shots"][shot])
    doubled = text.replace('"shots": {', f'"shots": {{"{shot}": {body}, ', 1)
    assert doubled != text
    (tmp_path / "reconstruction.json").write_text(doubled)
    with pytest.raises(InputError, match=f"{shot}.* twice"):
        posed_images("opensfm", tmp_path / "reconstruction.json", src / "images")


def test_a_query_listed_twice_is_named_with_its_line(tmp_path):
    from pipeline.queries import read_queries_with_intrinsics
    line = "a/0000.jpg PINHOLE 64 48 50 50 32 24\n"
    (tmp_path / "q.txt").write_text(line + "b.jpg PINHOLE 64 48 50 50 32 24\n" + line)
    where = tmp_path / "q.txt"
    with pytest.raises(InputError, match=rf"{where}:3: query a/0000.jpg is listed twice \(first at line 1\)"):
        read_queries_with_intrinsics(tmp_path / "q.txt", tmp_path)


def test_a_map_with_one_image_twice_is_refused_whatever_its_source():
    """The one check of every map (``Scene``): COLMAP models and RGB-D frames included."""
    from pipeline.scene import CameraRecord, ImageRecord, Scene
    camera = CameraRecord("PINHOLE", 64, 48, (50, 50, 32, 24))
    images = [ImageRecord("a.jpg", Path("a.jpg"), camera, np.eye(3, 4), origin=f"model.txt:{k}") for k in (3, 9)]
    with pytest.raises(SceneError, match=r"model.txt:9: image a.jpg is listed twice \(first at model.txt:3\)"):
        Scene(images, np.zeros((0, 3)), [], [], np.zeros((0, 2)))


# -- byte-order marks: the one text reader ---------------------------------------------------------

@pytest.mark.parametrize("reader", ["queries", "poses", "pairs", "middlebury", "transforms", "kapture"])
def test_a_byte_order_mark_is_not_data_in_any_reader(shared, tmp_path, reader):
    """Before: a query list starting with one failed 'image file .../\ufeffa/0000.jpg is missing'."""
    from pipeline.queries import read_queries_with_intrinsics
    from pipeline.textfiles import read_pairs, read_poses
    if reader == "queries":
        (tmp_path / "q.txt").write_text(BOM + "a/0000.jpg PINHOLE 64 48 50 50 32 24\n", encoding="utf-8")
        assert read_queries_with_intrinsics(tmp_path / "q.txt", tmp_path)[0].name == "a/0000.jpg"
    elif reader == "poses":
        (tmp_path / "p.txt").write_text(BOM + "a.jpg 1 0 0 0 0 0 0\n", encoding="utf-8")
        assert read_poses(tmp_path / "p.txt").find("a.jpg") is not None
    elif reader == "pairs":
        (tmp_path / "p.txt").write_text(BOM + "q.jpg r.jpg\n", encoding="utf-8")
        assert read_pairs(tmp_path / "p.txt") == {"q.jpg": ["r.jpg"]}
    elif reader == "middlebury":
        par = _middlebury(shared, tmp_path)
        par.write_text(BOM + par.read_text(), encoding="utf-8")
        assert posed_images("middlebury", tmp_path)[0]
    elif reader == "transforms":
        path = _transforms(shared, tmp_path)
        path.write_text(BOM + path.read_text(), encoding="utf-8")
        assert len(posed_images("transforms", path)[0]) == 2
    else:
        shutil.copytree(shared / "data" / "virtual_gallery" / "mapping", tmp_path / "k", symlinks=True)
        for f in (tmp_path / "k" / "sensors").glob("*.txt"):
            f.write_text(BOM + f.read_text(), encoding="utf-8")
        assert len(posed_images("kapture", tmp_path / "k")[0]) == 12


def test_a_colmap_text_model_with_a_byte_order_mark_or_an_image_twice(shared, tmp_path):
    """pycolmap reads the model's files itself: a BOM failed in its parser ('Check failed: line_stream1 >>
    image_id ...'), and a second image of one name went on to COLMAP's database."""
    from pipeline.mapping.readers.colmap import read_colmap
    m = shared / "data" / "maupertuis"
    shutil.copytree(m / "reconstruction", tmp_path / "bom")
    for f in (tmp_path / "bom").glob("*.txt"):
        f.write_text(BOM + f.read_text(), encoding="utf-8")
    assert len(read_colmap(tmp_path / "bom", m / "images").images) == 4
    shutil.copytree(m / "reconstruction", tmp_path / "twice")
    lines = (tmp_path / "twice" / "images.txt").read_text().splitlines()
    first = next(k for k, line in enumerate(lines) if line and not line.startswith("#"))
    fields = lines[first].split()
    fields[0] = "99"
    (tmp_path / "twice" / "images.txt").write_text("\n".join(lines + [" ".join(fields), lines[first + 1]]) + "\n")
    with pytest.raises(SceneError, match=rf"{tmp_path / 'twice'}: COLMAP image_id \d+: image {fields[-1]} is listed "
                                         "twice"):
        read_colmap(tmp_path / "twice", m / "images")


# -- every camera model a format declares: honoured or refused; counts checked ------------------

def test_transforms_json_camera_models_are_honoured_or_refused(shared, tmp_path):
    """Before: OPENCV_FISHEYE with k1..k4 built an OPENCV camera with k3 and k4 dropped."""
    fisheye = dict(camera_model="OPENCV_FISHEYE", k1=0.1, k2=-0.02, k3=0.003, k4=-0.0004)
    images, _ = posed_images("transforms", _transforms(shared, tmp_path, **fisheye))
    assert images[0].camera.model == "OPENCV_FISHEYE"
    assert images[0].camera.params[4:] == pytest.approx((0.1, -0.02, 0.003, -0.0004))
    images, _ = posed_images("transforms", _transforms(shared, tmp_path / "k3", k1=0.1, k3=0.01))
    assert images[0].camera.model == "FULL_OPENCV" and images[0].camera.params[8] == pytest.approx(0.01)
    for top, words in ((dict(camera_model="EQUIRECTANGULAR"), "EQUIRECTANGULAR"), (dict(k4=0.1), "k4"),
                       (dict(camera_model="OPENCV_FISHEYE", p1=0.01), "tangential")):
        folder = tmp_path / words
        with pytest.raises(SceneError, match=words):
            posed_images("transforms", _transforms(shared, folder, **top))


def test_a_field_of_view_of_zero_is_refused_without_a_numpy_warning(shared, tmp_path):
    """Before: a numpy RuntimeWarning, then 'fl_y is Infinity'."""
    path = _transforms(shared, tmp_path)
    data = json.loads(path.read_text())
    del data["fl_x"]
    data["camera_angle_x"] = 0
    path.write_text(json.dumps(data))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SceneError, match="camera_angle_x is 0"):
            posed_images("transforms", path)


def test_a_middlebury_file_cut_short_is_refused_by_its_header(shared, tmp_path):
    """Before: header 47, 29 lines built 17 of 19 images and dropped two without a word."""
    _middlebury(shared, tmp_path, lambda lines: lines[:30])
    with pytest.raises(SceneError, match="header says 47 views but it lists 29"):
        posed_images("middlebury", tmp_path)


def test_an_opensfm_brown_camera_is_read_as_opencv(shared, tmp_path):
    """Before: accepted by the type check, then KeyError: 'focal'."""
    src = shared / "data" / "opensfm_berlin"
    model = json.loads((src / "reconstruction_example.json").read_text())
    for cam in model[0]["cameras"].values():
        w, h = cam["width"], cam["height"]
        cam.clear()
        cam.update(projection_type="brown", width=w, height=h, focal_x=0.9, focal_y=0.91, c_x=0.01, c_y=-0.02,
                   k1=-0.1, k2=0.01, p1=0.001, p2=-0.002, k3=0.0)
    (tmp_path / "r.json").write_text(json.dumps(model))
    images, _ = posed_images("opensfm", tmp_path / "r.json", src / "images")
    camera = images[0].camera
    s = max(camera.width, camera.height)
    assert camera.model == "OPENCV"
    assert camera.params == pytest.approx((0.9 * s, 0.91 * s, camera.width / 2 + 0.01 * s,
                                           camera.height / 2 - 0.02 * s, -0.1, 0.01, 0.001, -0.002))


def test_a_nan_in_poses_bounds_names_its_row(shared, tmp_path):
    """Before: 'expected N x 17 finite numbers, got (8, 17)' without the row."""
    beer = shared / "data" / "beer_capture"
    (tmp_path / "images").symlink_to(beer / "images")
    data = np.load(beer / "poses_bounds.npy")
    data[5, 3] = np.nan
    np.save(tmp_path / "poses_bounds.npy", data)
    with pytest.raises(SceneError, match="row 5 "):
        posed_images("llff", tmp_path)


def test_an_empty_image_folder_for_sfm_is_a_clear_error(tmp_path):
    """Before: an IndexError raised while building its own error message."""
    (tmp_path / "photos").mkdir()
    out = pixloc("build-map", "sfm", tmp_path / "photos", "--store", tmp_path / "m.zarr", "--sync")
    assert out.returncode == 2 and "SfM needs at least 2" in out.stderr and "Traceback" not in out.stderr


def test_poses_that_disagree_with_the_images_are_warned_about(shared, tmp_path, caplog):
    """Before: a transforms.json written with OpenCV axes (no y/z flip) built a map of 190 points
    instead of 7,043 without a warning. Four Herz-Jesus photos, their poses read with the wrong axes."""
    from PIL import Image

    from pipeline.mapping.readers.colmap import triangulate_known_poses
    from pipeline.mapping.readers.strecha import read_strecha
    from pipeline.scene import CameraRecord
    images = []
    for im in read_strecha(shared / "data" / "strecha" / "Herz-Jesus-P8")[:4]:  # at half size: a quarter of the SIFT
        with Image.open(im.path) as photo:
            photo.resize((im.camera.width // 2, im.camera.height // 2)).save(tmp_path / im.name, quality=95)
        camera = CameraRecord(im.camera.model, im.camera.width // 2, im.camera.height // 2,
                              tuple(v / 2 for v in im.camera.params))
        images.append(dataclasses_replace(im, path=tmp_path / im.name, camera=camera))
    flip = np.diag([1.0, -1.0, -1.0])
    wrong = [dataclasses_replace(im, cam_from_world=np.concatenate(
        [flip @ im.cam_from_world[:, :3], (flip @ im.cam_from_world[:, 3])[:, None]], 1)) for im in images]
    with caplog.at_level("WARNING", logger="pipeline.mapping.readers.colmap"):
        triangulate_known_poses(wrong, tmp_path, tmp_path / "wrong")
    assert "pose convention" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="pipeline.mapping.readers.colmap"):
        triangulate_known_poses(images, tmp_path, tmp_path / "right")
    assert "pose convention" not in caplog.text


def dataclasses_replace(obj, **changes):
    import dataclasses
    return dataclasses.replace(obj, **changes)


# -- settings from outside the command line ------------------------------------------------------

def test_environment_settings_are_checked_at_startup(tmp_path):
    """Before: PIXLOC_MAX_IMAGE_PIXELS=garbage failed every query and the run exited 0."""
    for name, value in (("PIXLOC_MAX_IMAGE_PIXELS", "garbage"), ("PIXLOC_MAX_IMAGE_PIXELS", "-3"),
                        ("PIXLOC_STORAGE_OPTIONS", "[1]")):
        out = pixloc("check-store", tmp_path / "none.zarr", env={name: value})
        assert out.returncode == 2 and name in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_a_device_that_does_not_exist_is_one_line(cli_run):
    """Before: --device tpu:7 gave a torch RuntimeError traceback."""
    args = [a for a in cli_run.args if a != "--sync"]
    out = pixloc(*args[:args.index("--output") + 1], cli_run.output.parent / "tpu", "--sync", "--device", "tpu:7")
    assert out.returncode == 2 and "--device tpu:7" in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_same_tag_that_nothing_carries_is_refused(stairs, tmp_path):
    """Before: --same-tag nosuchtag retrieved unrestricted while job.json and the report claimed it."""
    import dataclasses
    from workflows.localize import plan_localization
    job = dataclasses.replace(stairs.job, retrieval=dataclasses.replace(stairs.job.retrieval, same_tag="nosuchtag"))
    with pytest.raises(ValueError, match="--same-tag nosuchtag: no map image has it"):
        plan_localization(job, stairs.queries[:2], tmp_path / "out")


@pytest.mark.parametrize("damage", ["not hdf5", "truncated", "two sizes", "no map image"])
def test_hloc_descriptors_are_checked_once_at_the_start(stairs, tmp_path, damage):
    """Before: every query failed with h5py's or numpy's message and the file was not named."""
    import dataclasses

    import h5py
    from pipeline.localization import retrieval
    from pipeline.store.layout import open_store
    from workflows.localize import plan_localization
    path = tmp_path / "global.h5"
    names = [str(n) for n in open_store(stairs.job.store)["images/name"][:]]
    if damage == "not hdf5":
        path.write_text("name,descriptor\n")
    else:
        with h5py.File(path, "w") as f:
            for k, name in enumerate(names + [q.name for q in stairs.queries]):
                dim = 8 if damage == "two sizes" and k == 1 else 16
                f.create_dataset(f"{'other/' if damage == 'no map image' else ''}{name}/global_descriptor",
                                 data=np.ones(dim, np.float32))
        if damage == "truncated":
            path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    retrieval.hloc_descriptors.cache_clear()
    job = dataclasses.replace(stairs.job, retrieval=retrieval.HlocDescriptors(k=stairs.job.retrieval.k,
                                                                              descriptors=str(path)))
    with pytest.raises(InputError, match=str(path)):
        plan_localization(job, stairs.queries[:2], tmp_path / "out")


def test_units_given_to_the_report_are_escaped(cli_run, stairs, tmp_path):
    """Before: report --units '<img src=x onerror=...>' went raw into the table headers."""
    out = tmp_path / "out"
    shutil.copytree(cli_run.output, out)
    args = list(cli_run.args)
    args[args.index("--output") + 1] = out
    lst = args[args.index("list") + 1]
    result = pixloc("report", "list", lst, "--query-images", stairs.root, "--output", out, "--ground-truth",
                    args[args.index("--ground-truth") + 1], "--units", "<img src=x onerror=alert(1)>",
                    "--thresholds", "100,180")
    assert result.returncode == 0, result.stderr
    page = (out / "report.html").read_text()
    assert "<img src=x" not in page and "&lt;img src=x onerror=alert(1)&gt;" in page


def test_evaluate_without_a_job_does_not_call_scene_units_metres(cli_run, stairs, tmp_path):
    """Before: evaluate labelled thresholds in scene units as metres ('0.0371 m, 1 deg')."""
    out = tmp_path / "out"
    shutil.copytree(cli_run.output, out)
    (out / "job.json").unlink()
    args = list(cli_run.args)
    result = pixloc("evaluate", "list", args[args.index("list") + 1], "--query-images", stairs.root, "--output", out,
                    "--ground-truth", args[args.index("--ground-truth") + 1], "--thresholds", "0.0371,1")
    assert result.returncode == 0, result.stderr
    assert "0.0371 scene units, 1 deg" in result.stdout and "0.0371 m," not in result.stdout


# -- defaults that build small maps ---------------------------------------------------------------

def test_the_default_store_builds_a_four_image_map_at_320_px(shared, tmp_path):
    """Before: 'Too few feature samples (40) in the 4 images sampled to fit a PCA of 48 components'."""
    m = shared / "data" / "maupertuis"
    out = pixloc("build-map", "colmap", m / "reconstruction", "--images", m / "images", "--store", tmp_path / "m.zarr",
                 "--resize", 320, "--sync")
    assert out.returncode == 0, out.stderr[-1000:]
    assert "4 images extracted" in out.stdout and "fewer than its 48 components" in out.stderr
    check = pixloc("check-store", tmp_path / "m.zarr")
    assert check.returncode == 0 and "all chunks verified" in check.stdout, check.stdout


def test_a_pca_of_more_components_than_samples_keeps_the_samples_exactly():
    from pipeline.store.compression import fit_pca, project, reconstruct
    x = np.random.default_rng(0).normal(size=(10, 32)).astype(np.float32)
    mean, basis = fit_pca(x, 16)
    assert basis.shape == (32, 16)
    assert np.allclose(basis.T @ basis, np.eye(16), atol=1e-5)
    assert np.allclose(reconstruct(project(x, (mean, basis)), (mean, basis)), x, atol=1e-4)
    full_mean, full = fit_pca(np.random.default_rng(1).normal(size=(200, 32)), 16)
    assert np.allclose(full.T @ full, np.eye(16), atol=1e-5)
