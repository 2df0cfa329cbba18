"""The bag-of-words index (``pipeline.localization.bow``) and the retrieval benchmark's co-visibility."""

from types import SimpleNamespace

import numpy as np

from pipeline.localization.bow import BagOfWords, root_sift, train_vocabulary, vocabulary_size
from pipeline.scene import CameraRecord
from pipeline.queries import QueryRecord
from workflows.benchmarks.retrieval import covisible


def unit(x):
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def places(rng, n_places=12, per_place=40, dim=128):
    """Descriptor prototypes of each place (a place: the patterns one image of it sees)."""
    return [unit(np.abs(rng.normal(size=(per_place, dim)))) for _ in range(n_places)]


def observed(rng, protos, n=300, noise=0.05):
    """An image's descriptors: draws of its place's prototypes with noise."""
    return unit(protos[rng.integers(len(protos), size=n)] + noise * np.abs(rng.normal(size=(n, protos.shape[1]))))


def test_each_query_retrieves_the_image_of_its_place_first():
    rng = np.random.default_rng(0)
    protos = places(rng)
    index = BagOfWords.build([(10 + k, root_sift(observed(rng, p))) for k, p in enumerate(protos)], size=256)
    assert list(index.images) == [10 + k for k in range(len(protos))]
    for k, p in enumerate(protos):
        scores = index.scores(root_sift(observed(rng, p, n=150, noise=0.08)))
        assert np.argmax(scores) == k
        assert scores[k] > 0.3 and np.sort(scores)[-2] < 0.5 * scores[k]  # a clear margin over the others
    # the inverted file's scores are the cosines of the dense tf-idf vectors
    q = root_sift(observed(rng, protos[3]))
    words = np.argmax(q @ index.words.T, axis=1)
    c = np.bincount(words, minlength=len(index.words))
    v = np.sqrt(c) * index.idf
    dense = np.zeros((len(index.images), len(index.words)))
    np.add.at(dense, (index.image, np.repeat(np.arange(len(index.words)), np.diff(index.start))), index.weight)
    np.testing.assert_allclose(index.scores(q), dense @ (v / np.linalg.norm(v)), atol=1e-5)
    assert np.allclose(np.linalg.norm(dense, axis=1), 1, atol=1e-5)
    assert index.scores(np.zeros((0, 128), np.float32)).tolist() == [0.0] * len(protos)


def test_the_vocabulary_is_seeded_and_sized_by_the_descriptors():
    rng = np.random.default_rng(1)
    x = root_sift(unit(np.abs(rng.normal(size=(3000, 128)))))
    a, b = train_vocabulary(x, 64, iterations=3), train_vocabulary(x, 64, iterations=3)
    assert a.shape == (64, 128) and np.array_equal(a, b)
    assert np.allclose(np.linalg.norm(a, axis=1), 1, atol=1e-5)
    assert [vocabulary_size(n) for n in (0, 25_600, 200_000, 10**8)] == [256, 256, 2048, 8192]


def test_root_sift_is_the_hellinger_kernel():
    rng = np.random.default_rng(2)
    d = unit(np.abs(rng.normal(size=(5, 128))))
    r = root_sift(d)
    p = d / d.sum(1, keepdims=True)
    np.testing.assert_allclose(r @ r.T, np.sqrt(p) @ np.sqrt(p).T, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1, atol=1e-5)


def _pose(centre, look_at):
    z = np.asarray(look_at, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross([0, 1, 0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return np.concatenate([R, (-R @ centre)[:, None]], 1)


def test_a_map_image_of_the_other_side_is_not_covisible():
    """Points on a thin wall seen from both sides: from the front, the front camera sees them all, a
    camera behind the wall sees the same points project into the query's image but from the other side."""
    g = np.linspace(-1, 1, 10)
    xyz = np.array([[x, y, 0.0] for x in g for y in g])
    front, side, back = _pose(np.array([0, 0, -4.0]), [0, 0, 0]), _pose(np.array([2.5, 0, -3.0]), [0, 0, 0]), \
        _pose(np.array([0, 0, 4.0]), [0, 0, 0])
    reader = SimpleNamespace(xyz=xyz, names=["front", "side", "back", "unusable"],
                             cam_from_world=[front, side, back, front], usable=lambda i: i < 3,
                             image_points=lambda i: np.arange(len(xyz)) if i != 1 else np.r_[np.arange(50), -1])
    camera = CameraRecord("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    query = QueryRecord("q", "q.jpg", camera, cam_from_world_gt=_pose(np.array([0.5, 0, -4.0]), [0, 0, 0]))
    assert covisible(reader, query).tolist() == [100, 50, 0, 0]
