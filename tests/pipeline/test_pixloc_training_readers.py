"""MegaDepth and CMU training layouts (official PixLoc info files), written here from a real
COLMAP model (maupertuis) in the official format and read back."""

import os
import pickle

import numpy as np
import pytest

from pipeline.mapping.readers.colmap import read_colmap
from pipeline.mapping.readers.pixloc_training import read_cmu_slice, read_info, read_megadepth
from pipeline.scene import SceneError
from pipeline.data.training_data import PairConfig
from workflows.training_sources import load_sources


def overlap(scene, a, b):
    pa = set(scene.obs_point[scene.obs_image == a])
    pb = set(scene.obs_point[scene.obs_image == b])
    return len(pa & pb) / max(1, min(len(pa), len(pb)))


@pytest.fixture(scope="module")
def model(shared):
    root = shared / "data" / "maupertuis"
    return read_colmap(root / "reconstruction", root / "images"), root / "images"


def observed(scene, i):
    return np.unique(scene.obs_point[scene.obs_image == i])


def K_of(camera):
    f, cx, cy = camera.params[:3]
    return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])


def test_megadepth_layout(model, tmp_path):
    scene, images = model
    n = len(scene.images)
    (tmp_path / "Undistorted_SfM" / "s0").mkdir(parents=True)
    os.symlink(images, tmp_path / "Undistorted_SfM" / "s0" / "images")
    (tmp_path / "megadepth_pixloc_training").mkdir()
    info = {"image_names": [im.name for im in scene.images],
            "poses": [(im.cam_from_world[:, :3], im.cam_from_world[:, 3]) for im in scene.images],
            "intrinsics": [K_of(im.camera) for im in scene.images], "points3D": scene.points,
            "p3D_observed": [observed(scene, i) for i in range(n)],
            "overlap_matrix": np.array([[overlap(scene, a, b) if a != b else 0 for b in range(n)] for a in range(n)])}
    with open(tmp_path / "megadepth_pixloc_training" / "s0.pkl", "wb") as f:
        pickle.dump(info, f)
    read, pairs = read_megadepth(tmp_path, "s0")
    assert [im.name for im in read.images] == [im.name for im in scene.images]
    assert all(im.path.is_file() for im in read.images)
    unique_obs = len(np.unique(np.stack([scene.obs_point, scene.obs_image]), axis=1).T)
    assert np.array_equal(read.points, scene.points) and len(read.obs_point) == unique_obs
    assert read.images[0].camera.width == round(2 * scene.images[0].camera.params[1])
    expected = {(a, b) for a in range(n) for b in range(n) if a != b and overlap(scene, a, b) > 0.3}
    assert set(pairs) == expected and pairs
    (source,), skipped = load_sources([{"kind": "megadepth", "path": ".", "scene": "s0"}], tmp_path, tmp_path, None)
    batch = source.dataset(PairConfig(max_size=256)).sample(np.random.default_rng(0))
    assert not skipped and batch.mask_points.sum() > 20


def test_cmu_layout(model, tmp_path):
    scene, images = model
    names = [f"img_{i:05d}_c{i % 2}_1303398475046031us.jpg" for i in range(len(scene.images))]
    for folder, idx in (("database", [0, 2]), ("query", [1, 3])):
        (tmp_path / "slice7" / folder).mkdir(parents=True)
        for i in idx:
            os.symlink(scene.images[i].path, tmp_path / "slice7" / folder / names[i])
    (tmp_path / "cmu_pixloc_training").mkdir()
    pose = [(im.cam_from_world[:, :3], im.cam_from_world[:, 3]) for im in scene.images]
    info = {"ref_image_names": [names[0], names[2]], "query_image_names": [names[1], names[3]],
            "ref_poses": [pose[0], pose[2]], "query_poses": [pose[1], pose[3]], "points3D": scene.points,
            "p3D_observed": [observed(scene, 0), observed(scene, 2)], "query_closest_indices": np.array([0, 1]),
            "query_overlap_matrix": np.array([[0.9, 0.1], [0.2, 0.8]])}
    with open(tmp_path / "cmu_pixloc_training" / "slice7.pkl", "wb") as f:
        pickle.dump(info, f)
    read, pairs = read_cmu_slice(tmp_path, 7)
    assert [im.tags["split"] for im in read.images] == ["ref", "ref", "query", "query"]
    assert read.images[2].camera.model == "OPENCV" and read.images[3].camera.params[0] == pytest.approx(873.382641)
    assert sorted(pairs) == [(0, 2), (1, 3)]  # (reference, query) where the overlap > 0.3
    (source,), _ = load_sources([{"kind": "cmu", "path": ".", "slice": 7}], tmp_path, tmp_path, None)
    assert source.init_range == (0.0, 0.0)  # official CMU training starts from the reference pose


def test_info_files_cannot_run_code(tmp_path):
    class Evil:
        def __reduce__(self):
            return (os.system, ("echo pwned",))
    path = tmp_path / "slice1.pkl"
    with open(path, "wb") as f:
        pickle.dump({"ref_image_names": Evil()}, f)
    with pytest.raises(SceneError, match="Refusing"):
        read_info(path)
