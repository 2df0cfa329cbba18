import numpy as np
import pytest
import torch

from pipeline.scene import CameraRecord
from pipeline.data.training_data import PairConfig, PairDataset, covisible_pairs, synthetic_scene
from pixloc.geometry import pose_error

CAMERA = CameraRecord("PINHOLE", 128, 96, (100.0, 100.0, 64.0, 48.0))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return synthetic_scene(tmp_path_factory.mktemp("syn"), 5, CAMERA, num_references=12, queries_per_condition=2)


def test_pairs_are_covisible_both_ways(scene):
    pairs = covisible_pairs(scene, 50)
    assert len(pairs) > 20
    assert set(pairs) == {(j, i) for i, j in pairs}
    for i, j in pairs[:10]:
        shared = np.intersect1d(scene.obs_point[scene.obs_image == i], scene.obs_point[scene.obs_image == j])
        assert len(shared) >= 50
    assert not any(i == j for i, j in pairs)


def test_pair_points_project_into_the_query_at_the_truth(scene):
    """The points of a pair, moved by the true relative pose, lie in front of the query camera
    and project inside its image."""
    ds = PairDataset([("syn", scene)], PairConfig(max_size=128, num_points=64))
    rng = np.random.default_rng(0)
    for _ in range(5):
        b = ds.sample(rng)
        p3d = b.query_from_ref_gt.transform(b.p3d_ref)[0][b.mask_points[0]]
        p2d, _ = b.camera_query[0].cam2image(p3d)
        assert (p3d[:, 2] > 0).all()
        # observed points project inside [0, size - 1] (up to float32 rounding at the border)
        assert ((p2d >= -1e-3) & (p2d <= torch.tensor([127.001, 95.001]))).all()


def test_initial_pose_lies_between_reference_and_truth(scene):
    ds = PairDataset([("syn", scene)], PairConfig(max_size=128, init_range=(0.75, 1.0)))
    rng = np.random.default_rng(1)
    exact = ds.pair(3, rng, init_fraction=1.0)
    dR, dt = pose_error(exact.query_from_ref_init, exact.query_from_ref_gt)
    assert float(dR) < 1e-3 and float(dt) < 1e-5
    for f in (0.0, 0.5):
        b = ds.pair(3, np.random.default_rng(1), init_fraction=f)
        dR_f, _ = pose_error(b.query_from_ref_init, b.query_from_ref_gt)
        dR_0, _ = pose_error(b.query_from_ref_gt.__class__.from_Rt(torch.eye(3), torch.zeros(3)).reshape(1),
                             b.query_from_ref_gt)
        assert float(dR_f) == pytest.approx((1 - f) * float(dR_0), rel=1e-3, abs=1e-3)


def test_fixed_pairs_are_reproducible(scene):
    ds = PairDataset([("syn", scene)], PairConfig(max_size=128))
    a, b = ds.fixed(4, seed=3), ds.fixed(4, seed=3)
    for x, y in zip(a, b):
        assert torch.equal(x.p3d_ref, y.p3d_ref) and torch.equal(x.query_from_ref_init.data, y.query_from_ref_init.data)


def test_a_scene_without_pairs_is_refused(scene):
    with pytest.raises(ValueError, match="no image pairs"):
        PairDataset([("syn", scene)], PairConfig(min_covisible=10 ** 7))


def test_far_initial_poses_come_from_their_own_range(scene):
    """With far_init_prob, that share of pairs starts in far_init_range of the way to the truth."""
    conf = PairConfig(max_size=128, init_range=(0.9, 1.0), far_init_prob=0.5, far_init_range=(0.2, 0.3))
    ds = PairDataset([("syn", scene)], conf)
    rng = np.random.default_rng(2)
    fractions = []
    for _ in range(40):
        b = ds.pair(3, rng)
        dR, _ = pose_error(b.query_from_ref_init, b.query_from_ref_gt)
        dR_0, _ = pose_error(b.query_from_ref_gt.__class__.from_Rt(torch.eye(3), torch.zeros(3)).reshape(1),
                             b.query_from_ref_gt)
        fractions.append(1 - float(dR) / float(dR_0))
    fractions = np.array(fractions)
    far = fractions < 0.5
    assert ((fractions > 0.2 - 1e-3) & (fractions < 0.3 + 1e-3))[far].all()
    assert ((fractions > 0.9 - 1e-3) & (fractions < 1.0 + 1e-3))[~far].all()
    assert 10 <= far.sum() <= 30
