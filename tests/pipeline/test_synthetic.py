import numpy as np
import pytest
import torch

from pipeline.mapping.depth import rgbd_scene
from pipeline.scene import CameraRecord
from pipeline.data.synthetic import CONDITIONS, SyntheticConfig, SyntheticScene, generate, read_synthetic

CAMERA = CameraRecord("PINHOLE", 320, 240, (250.0, 250.0, 160.0, 120.0))


@pytest.fixture(scope="module")
def scene():
    return SyntheticScene(SyntheticConfig(seed=3))


@pytest.mark.parametrize("model,params", [("PINHOLE", (250.0, 240.0, 161.0, 119.0)),
                                          ("SIMPLE_RADIAL", (250.0, 160.0, 120.0, -0.05))])
def test_ground_truth_poses_project_scene_points_onto_their_pixels(scene, model, params):
    """Back-project rendered depth to 3D scene points, project them with the ground-truth pose
    and our camera model: they land on the pixels they were rendered at (< 0.5 px)."""
    camera = CameraRecord(model, 320, 240, params)
    T = scene.query_poses(1, seed=5)[0]
    _, depth = scene.render(camera, T, "day")
    v, u = np.nonzero(depth > 0)
    assert len(u) > 0.5 * depth.size
    cam = camera.to_pixloc(torch.float64)
    p2d = torch.from_numpy(np.stack([u, v], 1).astype(np.float64))
    p_cam = cam.image2cam(p2d) * torch.from_numpy(depth[v, u].astype(np.float64))[:, None]
    world = (p_cam.numpy() - T[:, 3]) @ T[:, :3]  # scene points
    p_back = torch.from_numpy(world @ T[:, :3].T + T[:, 3])
    reprojected, _ = cam.cam2image(p_back)
    assert (p_back[:, 2] > 0).all()
    err = (reprojected - p2d).norm(dim=-1)
    assert float(err.max()) < 0.5
    # and they lie on the scene's surfaces: casting again from another view hits them.
    T2 = scene.reference_poses(8)[0]
    _, depth2 = scene.render(camera, T2, "day")
    assert (depth2 > 0).mean() > 0.5


def test_conditions_change_appearance_not_geometry(scene):
    T = scene.query_poses(1, seed=2)[0]
    renders = {c: scene.render(CAMERA, T, c, seed=1) for c in CONDITIONS}
    day_img, day_depth = renders["day"]
    for c in ("dusk", "night"):
        img, depth = renders[c]
        assert np.array_equal(depth, day_depth)
        assert np.abs(img.astype(float) - day_img).mean() > 10
    night = renders["night"][0].astype(float)
    assert night.mean() < 0.9 * day_img.mean()  # darker, even after auto-exposure
    occluded_img, occluded_depth = renders["occluded"]
    closer = (occluded_depth > 0) & (occluded_depth < day_depth - 0.1)
    assert closer.mean() > 0.02  # objects in front of the camera


def test_seeded_and_deterministic():
    a = SyntheticScene(SyntheticConfig(seed=7))
    b = SyntheticScene(SyntheticConfig(seed=7))
    c = SyntheticScene(SyntheticConfig(seed=8))
    T = a.reference_poses(4)[1]
    assert np.array_equal(a.render(CAMERA, T, "night", seed=2)[0], b.render(CAMERA, T, "night", seed=2)[0])
    assert not np.array_equal(a.render(CAMERA, T)[1], c.render(CAMERA, T)[1])


def test_generated_dataset_makes_an_rgbd_map(tmp_path):
    root = generate(tmp_path, SyntheticConfig(seed=1), num_references=12, queries_per_condition=1, camera=CAMERA)
    mapping, queries = read_synthetic(root)
    assert len(mapping) == 12 and [q.tags["condition"] for q in queries] == list(CONDITIONS)
    scene = rgbd_scene(mapping, method="frames", stride=16)
    assert len(scene.points) > 200 and scene.check() == {}


def test_photo_textures_cover_facades(tmp_path):
    import cv2
    photo = np.zeros((60, 80, 3), np.uint8)
    photo[..., 0], photo[..., 2] = 255, 255  # magenta (BGR), a colour the procedural textures never have
    cv2.imwrite(str(tmp_path / "photo.png"), photo)
    plain = SyntheticScene(SyntheticConfig(seed=3))
    textured = SyntheticScene(SyntheticConfig(seed=3, textures=(str(tmp_path / "photo.png"),)))
    magenta = []
    for scene in (plain, textured):
        count = 0
        for T in scene.reference_poses(8):
            img, _ = scene.render(CAMERA, T, "day")
            img = img.astype(int)
            count += int(((img[..., 0] > 2 * img[..., 1] + 20) & (img[..., 2] > 2 * img[..., 1] + 20)).sum())
        magenta.append(count)
    assert magenta[0] == 0 and magenta[1] > 0.02 * 8 * CAMERA.width * CAMERA.height


def test_a_generated_city_has_blocks_streets_and_tagged_views(tmp_path):
    """A 2x2 city: references along every street facing each block side, tagged by block side;
    each reference sees mostly the facade of the block its tag names (its depth hits lie in
    that block's footprint), and the dataset reads back like the courtyard's."""
    from pipeline.data.city import CityConfig, SyntheticCity, generate_city
    conf = CityConfig(seed=1, blocks=(2, 2), spacing=8.0)
    city = SyntheticCity(conf)
    views = city.reference_views()
    sides = {tag for _, tag in views}
    # every 8 m along the 24 m of each block side (crossings have no facade ahead: skipped)
    assert len(sides) == 2 * 2 * 4 and all(sum(t == side for _, t in views) == 3 for side in sides)
    camera = CameraRecord("PINHOLE", 80, 60, (62.5, 62.5, 40.0, 30.0))
    pitch = conf.block_size + conf.street
    share = []
    for T, tag in views[::3]:
        _, depth = city.render(camera, T, "day")
        v, u = np.nonzero(depth > 0)
        rays = np.stack([(u - 40.0) / 62.5, (v - 30.0) / 62.5, np.ones(len(u))], 1) * depth[v, u, None]
        world = (rays - T[:, 3]) @ T[:, :3]
        facade = world[world[:, 2] > 0.5]  # above the ground
        bx, by = (int(x) for x in tag.split("-")[:2])
        x0, y0 = conf.street + bx * pitch, conf.street + by * pitch
        inside = ((facade[:, 0] > x0 - 0.5) & (facade[:, 0] < x0 + conf.block_size + 0.5)
                  & (facade[:, 1] > y0 - 0.5) & (facade[:, 1] < y0 + conf.block_size + 0.5))
        assert len(facade) > 0.3 * depth.size and inside.mean() > 0.3, tag
        share.append(inside.mean())
    assert np.median(share) > 0.8  # near a crossing, a view along the street also sees the next block
    root = generate_city(tmp_path / "city", conf, queries_per_condition=1, camera=camera)
    mapping, queries = read_synthetic(root)
    assert len(mapping) == len(views) and len(queries) == len(CONDITIONS)
    assert {m.tags["block"] for m in mapping} == {"0-0", "0-1", "1-0", "1-1"}
    assert all(m.depth_path is not None for m in mapping)
    mtime = (root / "cameras.json").stat().st_mtime_ns
    generate_city(tmp_path / "city", conf, queries_per_condition=1, camera=camera)  # same settings: reused
    assert (root / "cameras.json").stat().st_mtime_ns == mtime


def test_a_photo_city_covers_every_facade_and_its_queries_stand_near_references(tmp_path):
    """The photo city of S2: with textures, every building's facades are photos (plaster and brick);
    its queries are drawn around the references, as the demo's are around its reference circle."""
    import cv2
    from pipeline.data.city import CityConfig, SyntheticCity
    photo = np.zeros((60, 80, 3), np.uint8)
    photo[..., 0], photo[..., 2] = 255, 255  # magenta (BGR)
    cv2.imwrite(str(tmp_path / "photo.png"), photo)
    city = SyntheticCity(CityConfig(seed=1, blocks=(1, 1), street=14.0, spacing=2.0,
                                    textures=(str(tmp_path / "photo.png"),)))
    camera = CameraRecord("PINHOLE", 80, 60, (62.5, 62.5, 40.0, 30.0))
    refs = city.reference_views()
    facade = []
    for T, _ in refs[::4]:
        img, depth = city.render(camera, T, "day")
        img = img.astype(int)
        magenta = (img[..., 0] > 2 * img[..., 1] + 20) & (img[..., 2] > 2 * img[..., 1] + 20)
        facade.append(magenta.sum() / max(int((depth > 0).sum()), 1))
    assert np.median(facade) > 0.5  # the facades, not only some buildings (the ground is not textured)
    centres = np.stack([-T[:, :3].T @ T[:, 3] for T, _ in refs])
    axes = np.stack([T[2, :3] for T, _ in refs])
    queries = city.query_views(20, seed=0, spread=0.5, near_references=True)
    for T, side in queries:
        c, axis = -T[:, :3].T @ T[:, 3], T[2, :3]
        d = np.linalg.norm(centres[:, :2] - c[:2], axis=1)
        k = int(np.argmin(d))
        assert d[k] < 2.0 and side in {tag for _, tag in refs}
        assert np.degrees(np.arccos(np.clip(axis @ axes[k], -1, 1))) < 30


def test_a_city_map_observes_only_points_within_reach_the_same_way(tmp_path):
    """On a city (frames far apart: most map points out of each frame's reach), observing only the points
    within reach of each depth map gives the observations of testing every point."""
    from pipeline.data.city import CityConfig, generate_city
    from pipeline.mapping.depth import frame_points, observe
    root = generate_city(tmp_path / "city", CityConfig(seed=1, blocks=(2, 2), spacing=8.0), queries_per_condition=0,
                         camera=CameraRecord("PINHOLE", 80, 60, (62.5, 62.5, 40.0, 30.0)))
    mapping, _ = read_synthetic(root)
    points = frame_points(mapping, stride=8)
    culled, every = observe(points, mapping), observe(points, mapping, cull=False)
    assert len(mapping) > 40 and len(culled[0]) > 5000
    for a, b in zip(culled, every):
        assert np.array_equal(a, b)
