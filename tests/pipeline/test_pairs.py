import numpy as np
import pytest

from pipeline.mapping.image_pairs import PairsConfig, read_pairs, retrieval_pairs, spatial_pairs, write_pairs
from pipeline.mapping.readers.strecha import read_strecha


def _ring(n: int, radius: float = 10.0):
    """n cameras on a circle, all looking at its centre."""
    poses = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        c = radius * np.array([np.cos(a), np.sin(a), 0.0])
        z = -c / np.linalg.norm(c)
        x = np.cross([0, 0, 1.0], z)
        R = np.stack([x, np.cross(z, x), z])
        poses.append(np.concatenate([R, -R @ c[:, None]], 1))
    return [f"{i:03d}.jpg" for i in range(n)], poses


def test_spatial_pairs_are_nearest_cameras_with_overlapping_views():
    names, poses = _ring(40)
    pairs = spatial_pairs(names, poses, num_neighbors=4, max_angle=60)
    assert len(pairs) == 40 * 4 // 2  # the ring: each image with its 2 neighbours on each side
    steps = {(int(b[:3]) - int(a[:3])) % 40 for a, b in pairs}
    assert steps <= {1, 2, 38, 39}
    # The opposite cameras are the farthest and look the other way: never paired.
    wide = spatial_pairs(names, poses, num_neighbors=39, max_angle=60)
    assert all(abs((int(b[:3]) - int(a[:3])) % 40 - 20) > 6 for a, b in wide)


def test_pairs_method_auto_is_exhaustive_only_for_small_maps():
    conf = PairsConfig()
    assert conf.resolve(conf.exhaustive_below - 1, posed=True) == "exhaustive"
    assert conf.resolve(conf.exhaustive_below, posed=True) == "spatial"
    assert conf.resolve(5000, posed=False) == "retrieval"
    assert PairsConfig(path="pairs.txt").resolve(10, posed=True) == "file"
    with pytest.raises(ValueError, match="Unknown pairs method"):
        PairsConfig("vocabtree")


def test_retrieval_pairs_take_the_most_similar_images():
    rng = np.random.default_rng(0)
    places = rng.normal(size=(5, 64))
    D = np.repeat(places, 4, 0) + 0.1 * rng.normal(size=(20, 64))  # 5 places, 4 photos each
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    names = [f"{i}.jpg" for i in range(20)]
    pairs = retrieval_pairs(names, D, num_neighbors=3)
    assert all(int(a[:-4]) // 4 == int(b[:-4]) // 4 for a, b in pairs) and len(pairs) == 5 * 6


def test_a_pairs_file_is_checked_against_the_images(tmp_path):
    names = ["a.jpg", "b.jpg", "c.jpg"]
    path = write_pairs([("a.jpg", "b.jpg"), ("b.jpg", "a.jpg"), ("b.jpg", "c.jpg")], tmp_path / "pairs.txt")
    assert read_pairs(path, names) == [("a.jpg", "b.jpg"), ("b.jpg", "c.jpg")]
    (tmp_path / "bad.txt").write_text("a.jpg b.jpg\na.jpg d.jpg\n")
    with pytest.raises(ValueError, match=r"bad.txt:2: image 'd.jpg' is not among"):
        read_pairs(tmp_path / "bad.txt", names)


def test_spatial_pairs_of_a_real_sequence(shared):
    """fountain-P11 is shot along an arc: each image's nearest cameras are its neighbours in the sequence."""
    images = read_strecha(shared / "data" / "strecha" / "fountain-P11")
    names = [im.name for im in images]
    pairs = spatial_pairs(names, [im.cam_from_world for im in images], num_neighbors=2)
    index = {n: i for i, n in enumerate(names)}
    assert len(pairs) <= 11 * 2 and {abs(index[a] - index[b]) for a, b in pairs} == {1, 2}
