import dataclasses

import numpy as np
import pytest
import torch
from torch.nn.functional import grid_sample

from pipeline.mapping.build import build_map
from pipeline.models import network
from pipeline.runtime import torch_threads
from pipeline.mapping.features import FeatureConfig
from pipeline.images import read_image, resize_max, to_tensor
from pipeline.scene import CameraRecord, Scene, SceneError
from pipeline.store.feature_groups import feature_key
from pipeline.store.layout import DONE, FAILED, StoreError, image_rows, open_store
from tests.pipeline.helpers import assert_same_store

CONF = FeatureConfig(resize=512, image_scales=(4, 1), dtype="float16")  # raw stored values are compared


@pytest.fixture(scope="module")
def built(maupertuis, tmp_path_factory):
    path = tmp_path_factory.mktemp("store") / "map.zarr"
    results = build_map(maupertuis, path, CONF)
    return path, results


def test_structure(built, maupertuis):
    path, results = built
    assert [r.status for r in results] == ["done"] * 4
    root = open_store(path)
    meta = root.attrs["pixloc_map"]
    assert meta["num_observations"] == 3355 and meta["num_points"] == 1039
    # Each image's block starts on a shard boundary: workers never share a file.
    assert meta["shard_rows"] % meta["chunk_rows"] == 0
    assert (root["images/row_start"][:] % meta["shard_rows"] == 0).all()
    for i in range(4):
        rows = image_rows(root, i)
        pts = root["observations/point"][rows]
        assert sorted(pts) == sorted(maupertuis.obs_point[maupertuis.obs_image == i])


def test_stored_features_equal_the_network_at_projections(built, maupertuis):
    """Recompute independently (numpy projection, torch grid_sample) and compare with the store."""
    path, _ = built
    root = open_store(path)
    group = root[f"features/{feature_key(CONF)}"]
    net, _ = network(CONF.model)
    i = 2
    image = maupertuis.images[i]
    rows = image_rows(root, i)
    xyz = root["points/xyz"][:][root["observations/point"][rows]]
    f, cx, cy = image.camera.params
    T = image.cam_from_world
    p = xyz @ T[:, :3].T + T[:, 3]
    uv_colmap = f * p[:, :2] / p[:, 2:] + [cx, cy]  # COLMAP pixel-corner convention
    rgb = read_image(image.path)
    edges = np.cumsum([0] + list(group.attrs["dims"]))
    for k, s in enumerate(CONF.image_scales):
        resized, (sx, _) = resize_max(rgb, CONF.resize // s)
        with torch.no_grad(), torch_threads(1):
            pred = net(to_tensor(resized)[None])
        for level, stride in enumerate(net.strides):
            fmap = pred["features"][level]
            h, w = fmap.shape[-2:]
            uv = uv_colmap * sx / stride - 0.5  # resized feature-map pixels, centre origin
            grid = torch.from_numpy(uv / [w - 1, h - 1] * 2 - 1).float()[None, None]
            expected = grid_sample(fmap, grid, align_corners=True)[0, :, 0].T.numpy()
            inside = (uv >= 2).all(1) & (uv <= [w - 3, h - 3]).all(1)
            stored = group[f"s{k}/features"][rows, edges[level]:edges[level + 1]].astype(np.float32)
            valid = group[f"s{k}/valid"][rows, level]
            assert np.array_equal(valid, inside)
            np.testing.assert_allclose(stored[valid], expected[valid], rtol=2e-3, atol=2e-3)


def test_rebuild_is_identical_and_skips_everything(built, maupertuis, tmp_path):
    path, _ = built
    again = build_map(maupertuis, path, CONF)
    assert again == []  # nothing pending
    fresh = tmp_path / "fresh.zarr"
    build_map(maupertuis, fresh, CONF)
    assert_same_store(path, fresh)


def test_another_model_or_config_is_refused(built, maupertuis, tmp_path):
    path, _ = built
    root = open_store(path, mode="r+")
    group = root[f"features/{feature_key(CONF)}"]
    digest = group.attrs["model_digest"]
    group.attrs["model_digest"] = "0000000000000000"
    try:
        with pytest.raises(StoreError, match="refusing to mix"):
            build_map(maupertuis, path, CONF)
    finally:
        group.attrs["model_digest"] = digest
    with pytest.raises(StoreError, match="holds another map"):
        build_map(maupertuis.subset([0, 1, 2]), path, CONF)
    with pytest.raises(StoreError, match="does not exist"):
        open_store(tmp_path / "missing.zarr")


def test_bad_images_fail_with_a_reason_and_the_rest_is_built(maupertuis, tmp_path):
    corrupt = tmp_path / "corrupt.jpg"
    corrupt.write_bytes(b"not a jpeg")
    images = list(maupertuis.images)
    images[0] = dataclasses.replace(images[0], path=tmp_path / "missing.jpg")
    images[1] = dataclasses.replace(images[1], path=corrupt)
    images[2] = dataclasses.replace(images[2], camera=CameraRecord("THIN_PRISM_FISHEYE", 100, 100, (1.0,) * 16))
    bad_pose = images[3].cam_from_world.copy()
    bad_pose[0, 3] = np.nan
    images.append(dataclasses.replace(images[3], name="nan_pose.jpg", cam_from_world=bad_pose))
    scene = Scene(images, maupertuis.points, maupertuis.obs_point, maupertuis.obs_image, maupertuis.obs_xy)
    results = build_map(scene, tmp_path / "map.zarr", CONF)
    group = open_store(tmp_path / "map.zarr")[f"features/{feature_key(CONF)}"]
    status, reasons = group["status"][:], [str(r) for r in group["reason"][:]]
    assert status.tolist() == [FAILED, FAILED, FAILED, DONE, FAILED]
    assert "missing" in reasons[0]
    assert "cannot be decoded" in reasons[1]
    assert "unsupported camera model 'THIN_PRISM_FISHEYE'" in reasons[2]
    assert "pose is not a finite" in reasons[4]
    assert [(r.name, r.status) for r in results] == [("01.jpg", "failed"), ("03.jpg", "done")]


def test_empty_model_is_a_clear_error(tmp_path, maupertuis):
    empty = Scene(maupertuis.images, np.zeros((0, 3)), [], [], np.zeros((0, 2)))
    with pytest.raises(SceneError, match="no 3D points"):
        build_map(empty, tmp_path / "map.zarr", CONF)


def test_one_file_per_image_and_array(built):
    """Layout 3 shards every per-row array by image block: version 2 wrote one file per chunk
    (~155 files per image on the demo)."""
    path, _ = built
    root = open_store(path)
    files = [f for f in path.rglob("*") if f.is_file()]
    data = [f for f in files if f.name != "zarr.json"]
    per_row = [f for f in data if "s0" in f.parts or "s1" in f.parts]
    num_images = root.attrs["pixloc_map"]["num_images"]
    # 2 scales x (features, confidences, valid), one shard each per image (the images fit one shard)
    assert len(per_row) == 2 * 3 * num_images
    # plus status, global, observations/point and xy per image, and a fixed number of small arrays
    # (the images' and points' arrays, and the finished build's consolidated status and global)
    assert len(data) <= 10 * num_images + 14


def test_int8_features_are_within_their_quantisation_step(built, maupertuis, tmp_path):
    """int8 codes with a float16 scale per row and level: within half a step of float16 storage."""
    from pipeline.store.reader import MapReader
    conf8 = dataclasses.replace(CONF, dtype="int8")
    build_map(maupertuis, tmp_path / "int8.zarr", conf8)
    path, _ = built
    half, small = MapReader(path, CONF), MapReader(tmp_path / "int8.zarr", conf8)
    assert "_p2_int8" in feature_key(conf8)
    obs = half.observations([0, 1, 2, 3], 1)
    for k in range(len(CONF.image_scales)):
        for (F, W, V), (F8, W8, V8) in zip(half.features(obs, k), small.features(obs, k)):
            step = np.abs(F).max(1, keepdims=True) / 127
            assert np.array_equal(V, V8) and np.array_equal(W, W8)
            assert (np.abs(F8 - F) <= 0.5 * step + 2e-3 * np.abs(F) + 1e-6).all()
            assert np.abs(F8 - F).mean() > 0  # it is quantised
    sizes = {c: sum(f.stat().st_size for f in (p / "features" / feature_key(c)).rglob("*") if f.is_file())
             for c, p in ((CONF, path), (conf8, tmp_path / "int8.zarr"))}
    assert sizes[conf8] < 0.6 * sizes[CONF]
    with pytest.raises(ValueError, match="Unknown feature storage type"):
        FeatureConfig(dtype="int4")


def test_pca_storage_reconstructs_the_features_and_keeps_its_bases(built, maupertuis, tmp_path):
    """--pca 48 with int8, two image scales: the 128-channel levels are stored as 48 principal components
    (bases fitted on the map's images, kept in the group), the 32-channel level as it is; readers
    reconstruct every channel, close to float16 storage (measured: median cosine 0.9994 and 0.982 at
    the two reduced levels of image scale 1), and the features take under 0.35 of float16."""
    from pipeline.store.reader import MapReader
    from pipeline.store.layout import check_feature_group, stored_dims
    conf = dataclasses.replace(CONF, dtype="int8", pca=48)
    assert feature_key(conf).endswith("_pca48") and "_int8_" in feature_key(conf)
    # a group recorded before pca and sift existed has no such keys: made with pca and sift 0
    assert CONF.made({k: v for k, v in CONF.to_dict().items() if k not in ("pca", "sift")}) and not conf.made(
        {k: v for k, v in conf.to_dict().items() if k not in ("pca", "sift")})
    path8 = tmp_path / "pca.zarr"
    assert [r.status for r in build_map(maupertuis, path8, conf)] == ["done"] * 4
    root = open_store(path8)
    group = root[f"features/{feature_key(conf)}"]
    check_feature_group(group, root.attrs["pixloc_map"], path8)
    assert stored_dims(group) == [32, 48, 48] and group["s1/features"].shape[1] == 128
    basis = group["s1/pca_basis_2"][:]
    assert basis.shape == (128, 48) and np.allclose(basis.T @ basis, np.eye(48), atol=1e-4)  # orthonormal
    path, _ = built
    half, small = MapReader(path, CONF), MapReader(path8, conf)
    obs = half.observations([0, 1, 2, 3], 1)
    for k in range(len(CONF.image_scales)):
        for level, ((F, W, V), (F8, W8, V8)) in enumerate(zip(half.features(obs, k), small.features(obs, k))):
            assert F8.shape == F.shape and np.array_equal(V, V8) and np.array_equal(W, W8)
            # the alignment compares L2-normalised features: their cosine to the full ones
            cos = (F * F8).sum(1)[V] / (np.linalg.norm(F, axis=1) * np.linalg.norm(F8, axis=1))[V]
            assert not V.any() or np.median(cos) > (0.995 if level == 0 else 0.95), (k, level, np.median(cos))
    sizes = {c: sum(f.stat().st_size for f in (p / "features" / feature_key(c)).rglob("*") if f.is_file())
             for c, p in ((CONF, path), (conf, path8))}
    assert sizes[conf] < 0.35 * sizes[CONF]
    assert build_map(maupertuis, path8, conf) == []  # nothing pending; the bases are kept
    build_map(maupertuis, tmp_path / "again.zarr", conf)
    assert_same_store(path8, tmp_path / "again.zarr")  # the same images give the same bases and codes
    with pytest.raises(ValueError, match="pca must be 0"):
        FeatureConfig(pca=-1)


def _first_session(scene, keep):
    """The scene of images ``keep`` with only the points they see (as an SfM of them would have)."""
    sub = scene.subset(keep)
    used = np.unique(sub.obs_point)
    index = -np.ones(len(scene.points), np.int64)
    index[used] = np.arange(len(used))
    return Scene(sub.images, scene.points[used], index[sub.obs_point], sub.obs_image, sub.obs_xy,
                 scene.point_ids[used])


def test_adding_a_session_to_a_store_of_principal_components_and_sift(maupertuis, tmp_path):
    """Before: adding a session to a --pca store resized the PCA bases as if they were rows, and the
    new image's features failed to project (ValueError: operands could not be broadcast). The
    bases are kept; the per-observation arrays (features, SIFT descriptors) grow with the rows."""
    from pipeline.store.reader import MapReader
    conf = FeatureConfig(resize=256, image_scales=(1,), pca=8, sift=640)
    path = tmp_path / "map.zarr"
    build_map(_first_session(maupertuis, [0, 1, 2]), path, conf)
    group = open_store(path)[f"features/{feature_key(conf)}"]
    bases = {name: a[:] for name, a in group["s0"].arrays() if name.startswith("pca_")}
    assert [r.status for r in build_map(maupertuis, path, conf)] == ["done"]
    group = open_store(path)[f"features/{feature_key(conf)}"]
    assert all(np.array_equal(group["s0"][name][:], b) for name, b in bases.items())
    reader = MapReader(path, conf)
    assert all(reader.sift_descriptors(i).shape == (n, 128) for i, n in enumerate(reader.num_obs))
    cover = [reader.sift_descriptors(i).any(1).mean() for i in range(4)]
    assert min(cover) > 0.02 and cover[3] > 0.5 * np.mean(cover[:3]), cover  # the new image's own, not fill


def test_an_image_whose_rows_are_all_fill_values_is_not_missing(maupertuis, tmp_path):
    """Before: zarr leaves out a shard whose rows are all fill values, so an image whose SIFT
    descriptors were all zeros (no keypoint within 2 px of its observations; virtual_gallery's
    rgb_00224) read as a missing file and failed every query that used it."""
    from pipeline.store.check import check_store
    from pipeline.store.reader import MapReader
    conf = FeatureConfig(resize=128, image_scales=(1,), sift=64)  # at 64 px, hardly a keypoint
    build_map(maupertuis, tmp_path / "map.zarr", conf)
    reader = MapReader(tmp_path / "map.zarr", conf)
    stored = [reader.sift_descriptors(i) for i in range(len(reader.names))]  # no StoreReadError
    assert any(not d.any() for d in stored) and check_store(tmp_path / "map.zarr").ok


def test_an_image_without_observations_is_not_missing(maupertuis, tmp_path):
    """The same class for the map's structure: an image that observes no point (a photo that a
    triangulation from known poses could not match: beer_capture with one of its files damaged) has no
    observation rows, and its all-fill block of the structure arrays is not written. Before: check-store
    named that block a missing file of the structure ("rebuild the store"), and every query with that
    image among its references failed."""
    from pipeline.store.check import check_store
    from pipeline.store.reader import MapReader
    keep = maupertuis.obs_image != 1
    scene = dataclasses.replace(maupertuis, obs_point=maupertuis.obs_point[keep],
                                obs_image=maupertuis.obs_image[keep], obs_xy=maupertuis.obs_xy[keep])
    conf = FeatureConfig(resize=128, image_scales=(1,))
    build_map(scene, tmp_path / "map.zarr", conf)
    checked = check_store(tmp_path / "map.zarr")
    assert checked.ok, checked.bad
    reader = MapReader(tmp_path / "map.zarr", conf)
    assert reader.num_obs[1] == 0 and reader.num_obs[0] > 0
    seen = reader.observations([0, 1, 2], 1)  # no StoreReadError for image 1
    assert len(seen.point) > 0 and 1 not in set(seen.db.tolist())


def test_adding_a_mapping_session_extracts_only_the_new_images(built, maupertuis, tmp_path, monkeypatch):
    """A map of 3 images, then the model extended with a 4th: the store keeps its rows, adds the new
    image, its observations and the points only it sees (the others matched by COLMAP id), and
    only the new image is extracted. An add interrupted before its commit leaves the old map."""
    from pipeline.store import structure as store_module
    from pipeline.store.reader import MapReader
    path = tmp_path / "map.zarr"
    first = _first_session(maupertuis, [0, 1, 2])
    assert [r.status for r in build_map(first, path, CONF)] == ["done"] * 3
    before = {k: v.copy() for k, v in (("rows", open_store(path)["images/row_start"][:]),)}

    real = store_module.extend_store

    def interrupted(root, scene):
        meta = dict(root.attrs["pixloc_map"])
        real(root, scene)
        root.attrs["pixloc_map"] = meta  # as if the commit had not been written
        raise KeyboardInterrupt
    monkeypatch.setattr(store_module, "extend_store", interrupted)
    with pytest.raises(KeyboardInterrupt):
        build_map(maupertuis, path, CONF)
    old = open_store(path)
    assert old.attrs["pixloc_map"]["num_images"] == 3 and old["images/name"].shape[0] == 4  # longer, uncommitted
    assert MapReader(path, CONF).names == [im.name for im in first.images]
    monkeypatch.setattr(store_module, "extend_store", real)

    results = build_map(maupertuis, path, CONF)  # the add runs again, then extraction
    assert [(r.name, r.status) for r in results] == [(maupertuis.images[3].name, "done")]
    root = open_store(path)
    meta = root.attrs["pixloc_map"]
    assert meta["num_images"] == 4 and meta["num_observations"] == len(maupertuis.obs_point)
    assert meta["num_points"] == len(np.unique(maupertuis.obs_point))  # seen points: old + those only #4 sees
    assert np.array_equal(root["images/row_start"][:3], before["rows"])  # stored rows untouched
    # image 4's features equal those of a map built at once, point by point
    full, _ = built
    a, b = MapReader(path, CONF), MapReader(full, CONF)
    ids_a = a.point_source_id[a.observations([3], 1).point]
    ids_b = b.point_source_id[b.observations([3], 1).point]
    assert sorted(ids_a) == sorted(ids_b)
    fa = a.features(a.observations([3], 1), 1)[0][0][np.argsort(ids_a)]
    fb = b.features(b.observations([3], 1), 1)[0][0][np.argsort(ids_b)]
    np.testing.assert_array_equal(fa, fb)
    by_id = dict(zip(maupertuis.point_ids, maupertuis.track_length))
    assert all(by_id[s] == t for s, t in zip(a.point_source_id, a.track_length))  # tracks count both sessions
    assert build_map(maupertuis, path, CONF) == []  # a rerun is a no-op


def test_reader_block_cache_is_bounded_and_counts_hits(built):
    from pipeline.store.reader import MapReader
    path, _ = built
    reader = MapReader(path, CONF)
    obs = reader.observations([0, 1], 1)
    first = reader.features(obs, 1)
    again = reader.features(obs, 1)
    assert reader.stats["blocks"] == 2 and reader.stats["hits"] == 2 and reader.stats["bytes"] > 0
    # cached as stored, decoded per call: the cache holds the bytes read, not their float32 decoding
    assert reader._cached_bytes == reader.stats["bytes"]
    for (f, w, v), (f2, w2, v2) in zip(first, again):
        assert f.dtype == np.float32 and np.array_equal(f, f2) and np.array_equal(w, w2) and np.array_equal(v, v2)
    some = reader.observations([1], 1)
    some = type(some)(some.point[::3], some.db[::3], some.rows[::3])  # a subset of an image's rows
    for (f, w, v), (F, W, V) in zip(reader.features(some, 1), first):
        at = np.flatnonzero(obs.db == 1)[::3]
        assert np.array_equal(f, F[at]) and np.array_equal(w, W[at]) and np.array_equal(v, V[at])
    one = reader._cached_bytes // 2
    small = MapReader(path, CONF, cache_bytes=int(1.2 * one))  # room for about one block
    for _ in range(2):  # a call reads its missing blocks together: the last one read stays
        small.features(obs, 1)
    assert small.stats["blocks"] == 3 and small.stats["hits"] == 1 and len(small._blocks) == 1


def test_a_finished_build_is_consolidated_for_fast_opening(built, maupertuis, tmp_path):
    """Per-image status and global arrays are copied into one chunk each when a build finishes
    (6,697 one-image chunks took 3.4 s each to read at open); a new build or an add undoes it."""
    from pipeline.store.reader import MapReader
    from pipeline.store.layout import consolidated
    path, _ = built
    root = open_store(path)
    group = root[f"features/{feature_key(CONF)}"]
    assert consolidated(group, root.attrs["pixloc_map"])
    reader = MapReader(path, CONF)
    assert reader.static and np.array_equal(reader.status, group["status"][:])
    np.testing.assert_array_equal(reader.global_descriptors, group["global"][:])
    partial = tmp_path / "partial.zarr"
    from pipeline.mapping.build import extract_features, write_structure
    write_structure(maupertuis, partial, CONF)
    extract_features(partial, CONF, [0])  # a build under way (or killed): not consolidated
    assert not MapReader(partial, CONF).static and MapReader(partial, CONF).usable(0)


def test_a_feature_setting_added_later_keeps_the_keys_of_earlier_groups():
    """Before: a new FeatureConfig field needed its own line in feature_key, or two configs that differ
    in it shared one group; now it is named where it differs from its default, and a group recorded
    without it reads as made with its default."""
    @dataclasses.dataclass(frozen=True)
    class Later(FeatureConfig):
        blur: int = 0
    assert feature_key(Later()) == feature_key(FeatureConfig())
    assert feature_key(Later(blur=2)) == feature_key(FeatureConfig()) + "_blur2"
    assert Later().made(FeatureConfig().to_dict()) and not Later(blur=2).made(FeatureConfig().to_dict())
