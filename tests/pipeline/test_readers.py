import json
import shutil

import numpy as np
import pytest
import torch

from pipeline.mapping.build import build_map
from pipeline.mapping.depth import depth_camera, load_depth, densify, rgbd_scene
from pipeline.mapping.image_pairs import PairsConfig
from pipeline.progress import Silent
from pipeline.mapping.readers.colmap import (cached_model, images_fingerprint, legacy_fingerprint, read_colmap, run_sfm,
                                     triangulate_known_poses)
from pipeline.mapping.readers.kapture import read_kapture
from pipeline.mapping.readers.rgbd import read_7scenes, read_pose_txt
from pipeline.mapping.readers.strecha import read_strecha
from pipeline.mapping.features import FeatureConfig
from pipeline.scene import CameraRecord, Scene, SceneError
from pipeline.store.feature_groups import feature_key
from pipeline.store.layout import open_store


def reprojection_errors(scene: Scene) -> np.ndarray:
    """Pixel distance between each observation and its point projected with our camera model."""
    errors = []
    for i, im in enumerate(scene.images):
        sel = scene.obs_image == i
        p2d, _ = im.camera.to_pixloc(torch.float64).cam2image(
            im.pose(torch.float64).transform(torch.from_numpy(scene.points[scene.obs_point[sel]])))
        errors.append(np.linalg.norm(p2d.numpy() + 0.5 - scene.obs_xy[sel], axis=1))
    return np.concatenate(errors)


def test_colmap_text_model(maupertuis):
    assert len(maupertuis.images) == 4 and len(maupertuis.points) == 1039 and len(maupertuis.obs_point) == 3355
    assert maupertuis.images[0].camera.model == "SIMPLE_PINHOLE"
    assert maupertuis.check() == {}
    # COLMAP's own mean reprojection error is 0.34 px: our projection must agree.
    assert np.mean(reprojection_errors(maupertuis)) < 0.5


def test_strecha_known_poses_triangulate_below_one_pixel(shared, tmp_path):
    """With spatial pairs (4 nearest cameras each): 25 pairs matched instead of 55."""
    root = shared / "data" / "strecha" / "fountain-P11"
    scene = triangulate_known_poses(read_strecha(root), root / "images", tmp_path,
                                    pairs=PairsConfig("spatial", num_neighbors=4))
    assert len((tmp_path / "pairs.txt").read_text().splitlines()) <= 30  # exhaustive: 55
    assert len(scene.images) == 11 and len(scene.points) > 5000
    assert scene.track_length.min() >= 2
    assert np.median(reprojection_errors(scene)) < 1.0
    # The dataset copied elsewhere (new file times, same bytes): the triangulation is reused, not
    # redone (pycolmap would give another map, which a store built from the first one refuses).
    copy = tmp_path / "copy"
    shutil.copytree(root / "images", copy, copy_function=shutil.copyfile)
    written = {f: f.stat().st_mtime_ns for f in (tmp_path / "model").iterdir()}
    again = triangulate_known_poses(read_strecha(root), copy, tmp_path, pairs=PairsConfig("spatial", num_neighbors=4))
    assert {f: f.stat().st_mtime_ns for f in (tmp_path / "model").iterdir()} == written  # not rewritten
    assert np.array_equal(again.points, scene.points) and np.array_equal(again.obs_xy, scene.obs_xy)
    # Changed bytes are another input.
    names = [im.name for im in read_strecha(root)]
    before = images_fingerprint(copy, names)
    with open(copy / names[3], "r+b") as f:
        f.seek(1000)
        byte = f.read(1)
        f.seek(1000)
        f.write(bytes([byte[0] ^ 1]))
    after = images_fingerprint(copy, names)
    assert [a == b for a, b in zip(before["images"], after["images"])] == [n != names[3] for n in names]


def test_a_work_folder_of_the_older_format_is_reused(shared, tmp_path):
    """Markers written before content digests (size and file time) are accepted while the
    files are untouched, and rewritten in the new format."""
    import pycolmap
    image_dir = shared / "data" / "strecha" / "fountain-P11" / "images"
    names = sorted(p.name for p in image_dir.iterdir())[:2]
    fingerprint = images_fingerprint(image_dir, names, kind="sfm")
    marker = tmp_path / "sfm.json"
    marker.write_text(json.dumps(legacy_fingerprint(image_dir, fingerprint)))
    pycolmap.Reconstruction().write(str((tmp_path / "model").mkdir() or tmp_path / "model"))
    assert cached_model(tmp_path, "sfm.json", "model", fingerprint, image_dir) is not None
    assert json.loads(marker.read_text()) == fingerprint
    marker.write_text(json.dumps({**fingerprint, "kind": "triangulation"}))  # other settings
    assert cached_model(tmp_path, "sfm.json", "model", fingerprint, image_dir) is None


def test_kapture_rig_poses(shared, tmp_path):
    root = shared / "data" / "virtual_gallery" / "mapping"
    images = read_kapture(root)
    assert len(images) == 12 and {im.tags["camera"] for im in images} == {"training_camera_0", "training_camera_1"}
    assert all(im.tags["rig"] == "training_rig" for im in images)
    # The two cameras of one rig frame: 60 degrees apart, as rigs.txt says.
    a, b = images[0], images[1]
    R = b.cam_from_world[:, :3] @ a.cam_from_world[:, :3].T
    assert np.degrees(np.arccos((np.trace(R) - 1) / 2)) == pytest.approx(60.0, abs=1e-3)
    # The rig convention (sensor_from_rig) is the one under which matches triangulate.
    scene = triangulate_known_poses(images, root / "sensors" / "records_data", tmp_path)
    assert len(scene.points) > 3000 and np.median(reprojection_errors(scene)) < 1.0
    # the query session: four photos of four focal lengths, each with its ground-truth pose
    from pipeline.mapping.readers.sources import load_queries
    queries = load_queries("kapture", root.parent / "query")
    assert len(queries) == 4 and len({q.camera.params[0] for q in queries}) == 4
    assert all(np.isfinite(q.cam_from_world_gt).all() for q in queries)


class Recorded(Silent):
    """A progress counter that keeps each stage's updates."""
    stages = {}

    def __init__(self, total, desc, unit, plural=None):
        super().__init__(total, desc, unit)
        self.stages[desc] = (total, self.steps)

    @property
    def steps(self):
        self.__dict__.setdefault("_steps", [])
        return self._steps

    def update(self, n=1):
        super().update(n)
        self.steps.append(n)


def test_sfm_of_sacre_coeur_then_a_store(shared, tmp_path):
    scene = run_sfm(shared / "data" / "sacre_coeur" / "mapping", tmp_path, progress=Recorded)
    assert len(scene.images) >= 8 and len(scene.points) > 1000
    # each stage counted while it ran, in images and pairs, up to what it did
    stages = Recorded.stages
    assert stages["SIFT features"][0] == 10 and sum(stages["SIFT features"][1]) == 10
    assert len(stages["SIFT features"][1]) >= 3  # counted during the call, not once at its end
    assert stages["SIFT matching"][0] == 45 and sum(stages["SIFT matching"][1]) == 45
    assert sum(stages["SfM registration"][1]) == len(scene.images)
    assert np.mean(reprojection_errors(scene)) < 1.5
    conf = FeatureConfig(resize=512, image_scales=(1,))
    results = build_map(scene, tmp_path / "map.zarr", conf)
    assert [r.status for r in results] == ["done"] * len(scene.images)
    group = open_store(tmp_path / "map.zarr")[f"features/{feature_key(conf)}"]
    assert group["s0/valid"][:, 0].sum() > 0.9 * len(scene.obs_point)


def test_7scenes_rgbd_map_lies_on_the_depth_surface(shared):
    images = read_7scenes(shared / "data" / "7scenes_stairs", [2, 3])
    assert len(images) == 6
    scene = rgbd_scene(images, method="tsdf")
    assert len(scene.points) > 5000 and scene.track_length.min() >= 2
    gaps = []
    for i, im in enumerate(images):  # every frame that observes a point, not only the one it came from
        sel = scene.obs_image == i
        T = im.depth_from_world()  # the depth sensor's pose: 2.5 cm from the colour camera's
        p_cam = scene.points[scene.obs_point[sel]] @ T[:, :3].T + T[:, 3]
        uv = np.round(depth_camera(im).cam2image(torch.from_numpy(p_cam))[0].numpy()).astype(int)
        gaps.append(np.abs(p_cam[:, 2] - load_depth(im)[uv[:, 1], uv[:, 0]]))
    gaps = np.concatenate(gaps)
    assert np.median(gaps) < 0.01 and np.mean(gaps < 0.02) > 0.8


def test_rgbd_pose_txt_frames(shared):
    root = shared / "data" / "rgbd_slambook" / "kinect_room"
    cam = CameraRecord("PINHOLE", 640, 480, (518.0, 519.0, 325.5, 253.5))
    images = read_pose_txt(root, cam, depth_scale=1e-3, depth_ext=".pgm")
    scene = rgbd_scene(images, method="frames", stride=8)
    assert len(images) == 5 and len(scene.points) > 1000


def test_densify_moves_points_onto_depth(shared):
    images = read_7scenes(shared / "data" / "7scenes_stairs", [2], color_from_depth=None)
    scene = rgbd_scene(images, method="frames", stride=16)
    noisy = Scene(scene.images, scene.points + np.random.default_rng(0).normal(0, 0.05, scene.points.shape),
                  scene.obs_point, scene.obs_image, scene.obs_xy)
    dense = densify(noisy)
    before = np.linalg.norm(noisy.points - scene.points, axis=1)
    after = np.linalg.norm(dense.points - scene.points, axis=1)
    assert np.median(after) < 0.2 * np.median(before)
    apart = read_7scenes(shared / "data" / "7scenes_stairs", [2])  # the depth sensor 2.5 cm away
    with pytest.raises(SceneError, match="depth sensor apart"):
        densify(Scene(apart, scene.points, scene.obs_point, scene.obs_image, scene.obs_xy))


def _warped_ncc(images) -> float:
    """Mean NCC of the grey levels at the points of each frame's depth seen in another frame's
    colour, at the frames' poses: how well the colour cameras are placed against the depth."""
    from pipeline.images import read_image
    grey = {im.name: read_image(im.path).astype(np.float64).mean(-1) for im in images}
    scores = []
    for a in images:
        depth = load_depth(a)
        v, u = np.mgrid[0:depth.shape[0]:4, 0:depth.shape[1]:4]
        keep = depth[v, u] > 0
        rays = depth_camera(a).image2cam(torch.from_numpy(np.stack([u[keep], v[keep]], -1).astype(np.float64)))
        T = a.depth_from_world()
        world = (rays.numpy() * depth[v, u][keep][:, None] - T[:, 3]) @ T[:, :3]
        values = []
        for im in images:
            p2d, valid = im.camera.to_pixloc(torch.float64).cam2image(im.pose(torch.float64).transform(
                torch.from_numpy(world)))
            uv = np.round(p2d.numpy()).astype(int)
            ok = valid.numpy() & (uv >= 0).all(1) & (uv[:, 0] < 640) & (uv[:, 1] < 480)
            values.append(np.where(ok, grey[im.name][np.clip(uv[:, 1], 0, 479), np.clip(uv[:, 0], 0, 639)], np.nan))
        for k, im in enumerate(images):
            if im.name != a.name:
                x, y = values[images.index(a)], values[k]
                ok = np.isfinite(x) & np.isfinite(y)
                x, y = x[ok] - x[ok].mean(), y[ok] - y[ok].mean()
                scores.append((x * y).sum() / np.sqrt((x * x).sum() * (y * y).sum()))
    return float(np.mean(scores))


def test_7scenes_colour_camera_is_placed_beside_the_depth_sensor(shared):
    """The poses of 7-Scenes are the depth sensor's; the colour camera is 2.5 cm beside it (the
    Kinect's baseline). Colour warped through depth between the map frames (sequences 2, 3)
    agrees better with it than with the colour camera at the depth pose (0.58 -> 0.66), and the
    other side is worse (0.50)."""
    root = shared / "data" / "7scenes_stairs"
    at_depth = _warped_ncc(read_7scenes(root, [2, 3], color_from_depth=None))
    beside = _warped_ncc(read_7scenes(root, [2, 3]))
    other_side = np.array([[1.0, 0, 0, 0.025], [0, 1, 0, 0], [0, 0, 1, 0]])
    wrong = _warped_ncc(read_7scenes(root, [2, 3], color_from_depth=other_side))
    assert beside > at_depth + 0.05 and wrong < at_depth - 0.05
    images = read_7scenes(root, [2])
    centre = -images[0].cam_from_world[:, :3].T @ images[0].cam_from_world[:, 3]
    depth_centre = -images[0].depth_from_world()[:, :3].T @ images[0].depth_from_world()[:, 3]
    assert abs(np.linalg.norm(centre - depth_centre) - 0.025) < 1e-5  # the files' rotations are orthonormal to 1e-5


def test_7scenes_calibration_file_overrides_the_default_and_bad_ones_are_named(shared, tmp_path):
    from pipeline.mapping.readers.rgbd import CALIBRATION_FILE
    (tmp_path / "seq-02").symlink_to(shared / "data" / "7scenes_stairs" / "seq-02")
    (tmp_path / CALIBRATION_FILE).write_text("1 0 0 -0.03\n0 1 0 0.01\n0 0 1 0\n0 0 0 1\n")
    image = read_7scenes(tmp_path, [2])[0]
    at_depth = read_7scenes(tmp_path, [2], color_from_depth=None)[0]
    assert np.allclose(image.cam_from_world[:, 3] - at_depth.cam_from_world[:, 3], (-0.03, 0.01, 0))
    assert np.allclose(image.depth_from_world(), at_depth.cam_from_world)
    for text in ("1 0 0\n0 1 0\n", "2 0 0 0\n0 1 0 0\n0 0 1 0\n", "a b c d\n"):
        (tmp_path / CALIBRATION_FILE).write_text(text)
        with pytest.raises(SceneError, match=CALIBRATION_FILE):
            read_7scenes(tmp_path, [2])


def test_bad_sources_are_named(tmp_path, shared):
    with pytest.raises(SceneError, match="does not exist"):
        read_colmap(tmp_path / "nope", tmp_path)
    with pytest.raises(SceneError, match="not a kapture dataset"):
        read_kapture(tmp_path)
    empty = Scene([], np.zeros((0, 3)), [], [], np.zeros((0, 2)))
    with pytest.raises(SceneError, match="no images"):
        empty.check()


def _triangulated(images, image_root, work):
    """The images' SIFT matches triangulated with the poses read (outliers kept up to 50 px, so that
    a wrong axis convention shows as large errors and points behind the cameras), and for each
    observation its reprojection error and whether the point is in front of the camera."""
    scene = triangulate_known_poses(images, image_root, work, max_reprojection_error=50.0)
    errors, front = [], []
    for i, im in enumerate(scene.images):
        sel = scene.obs_image == i
        p_cam = im.pose(torch.float64).transform(torch.from_numpy(scene.points[scene.obs_point[sel]]))
        front.append((p_cam[:, 2] > 0).numpy())
        p2d, _ = im.camera.to_pixloc(torch.float64).cam2image(p_cam)
        errors.append(np.linalg.norm(p2d.numpy() + 0.5 - scene.obs_xy[sel], axis=1))
    return scene, np.concatenate(errors), np.concatenate(front)


def test_middlebury_poses_triangulate_below_a_pixel(shared, tmp_path):
    from pipeline.mapping.readers.middlebury import read_middlebury
    root = shared / "data" / "middlebury" / "templeRing"
    images = read_middlebury(root)
    assert len(images) == 19 and images[0].camera.model == "PINHOLE"  # 47 views listed, 19 images present
    scene, errors, front = _triangulated(images[:6], root, tmp_path)
    assert len(scene.points) > 500 and np.median(errors) < 0.5 and front.mean() > 0.99


def test_bundler_poses_reproject_the_bundles_own_points_and_triangulate(shared, tmp_path):
    """Bundler's camera looks down -z with y up, and its image points are centred, y up."""
    from pipeline.mapping.readers.bundler import image_list, read_bundler
    root = shared / "data" / "bundler_kermit"
    bundle = root / "results.example" / "bundle.out"
    images = read_bundler(bundle, root)
    assert len(images) == 9 and images[0].camera.model == "RADIAL"  # 2 of the 11 cameras have f = 0: not posed
    by_camera = {k: im for im in images for k, name in enumerate(image_list(root)) if name == im.name}
    # the bundle's points, projected with the poses and cameras read, land on its observations
    lines = [line.split() for line in bundle.read_text().splitlines()[2 + 5 * 11:]]
    gaps = []
    for k in range(0, len(lines) - 2, 3):
        xyz = torch.tensor([[float(v) for v in lines[k]]], dtype=torch.float64)
        views = lines[k + 2]
        for j in range(int(views[0])):
            cam, x, y = int(views[1 + 4 * j]), float(views[3 + 4 * j]), float(views[4 + 4 * j])
            im = by_camera[cam]
            p2d, _ = im.camera.to_pixloc(torch.float64).cam2image(im.pose(torch.float64).transform(xyz))
            gaps.append(np.linalg.norm(p2d[0].numpy() + 0.5 - (x + im.camera.width / 2, im.camera.height / 2 - y)))
    assert len(gaps) > 1500 and np.median(gaps) < 1.0
    scene, errors, front = _triangulated(images[:6], root, tmp_path)
    assert len(scene.points) > 300 and np.median(errors) < 0.5 and front.mean() > 0.99


def test_llff_poses_are_the_colmap_models_and_triangulate(shared, tmp_path):
    """LLFF stores COLMAP's poses with its axes as (down, right, back): read back, they are the
    binary COLMAP model's to 1e-5 deg."""
    from pipeline.mapping.readers.llff import read_llff
    root = shared / "data" / "beer_capture"
    images = {im.name: im for im in read_llff(root)}
    model = read_colmap(root / "sparse" / "0", root / "images")
    assert len(images) == len(model.images) == 71
    for im in model.images:
        R = images[im.name].cam_from_world[:, :3] @ im.cam_from_world[:, :3].T
        assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 1e-5
        assert np.allclose(images[im.name].cam_from_world, im.cam_from_world, atol=1e-6)
    scene, errors, front = _triangulated([images[n] for n in sorted(images)[:6]], root / "images", tmp_path)
    assert len(scene.points) > 300 and np.median(errors) < 1.5 and front.mean() > 0.99


def test_opensfm_poses_triangulate_within_two_pixels(shared, tmp_path):
    """Axis-angle rotations world to camera; focal as a fraction of the larger side (3264 px)."""
    from pipeline.mapping.readers.opensfm import read_opensfm
    root = shared / "data" / "opensfm_berlin"
    images = read_opensfm(root / "reconstruction_example.json", root / "images")
    assert [im.name for im in images] == ["01.jpg", "02.jpg", "03.jpg"] and images[0].camera.model == "RADIAL"
    scene, errors, front = _triangulated(images, root / "images", tmp_path)
    assert len(scene.points) > 500 and np.median(errors) < 2.0 and front.mean() > 0.99


def test_transforms_json_of_known_poses_reads_back_and_triangulates(shared, tmp_path):
    """No shared scene comes as a transforms.json: the Strecha fountain's cameras written in its
    OpenGL convention (as nerfstudio's colmap2nerf does) read back to the same poses, and
    triangulate (an axis error would show as tens of pixels)."""
    from pipeline.mapping.readers.transforms import read_transforms
    root = shared / "data" / "strecha" / "fountain-P11"
    strecha = read_strecha(root)[:5]
    frames = []
    for im in strecha:
        R, t = im.cam_from_world[:, :3], im.cam_from_world[:, 3]
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R.T @ np.diag([1.0, -1.0, -1.0]), -R.T @ t
        fx, fy, cx, cy = im.camera.params
        frames.append({"file_path": f"images/{im.name[:-4]}", "transform_matrix": c2w.tolist(), "fl_x": fx,
                       "fl_y": fy, "cx": cx, "cy": cy, "w": im.camera.width, "h": im.camera.height})
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "images").symlink_to(root / "images")
    (tmp_path / "scene" / "transforms.json").write_text(json.dumps({"frames": frames}))
    images = read_transforms(tmp_path / "scene" / "transforms.json")
    assert [im.name for im in images] == [f"images/{im.name}" for im in strecha]  # the extension found
    for a, b in zip(images, strecha):
        assert np.allclose(a.cam_from_world, b.cam_from_world, atol=1e-9) and a.camera == b.camera
    scene, errors, front = _triangulated(images, tmp_path / "scene", tmp_path / "work")
    assert len(scene.points) > 1000 and np.median(errors) < 1.0 and front.mean() > 0.99


def test_observing_only_points_within_reach_finds_the_same_observations(shared):
    """``observe`` tests each frame only against the points within reach of its depth map (a k-d tree):
    the same observations as testing every point, on real RGB-D frames whose colour camera is apart from
    the depth sensor."""
    from pipeline.mapping.depth import frame_points, observe
    images = read_7scenes(shared / "data" / "7scenes_stairs", [2, 3])
    points = frame_points(images, stride=16)
    culled, every = observe(points, images), observe(points, images, cull=False)
    assert len(culled[0]) > 1000
    for a, b in zip(culled, every):
        assert np.array_equal(a, b)
