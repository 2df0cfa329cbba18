"""Starting poses of the search prior: turns about the camera centre, moves along the optical axis."""

from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.evaluate import pose_errors
from pipeline.localization.search import SearchConfig, perturbations, same_basin, screening_order


def _pose(seed=0):
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    return np.concatenate([R, rng.normal(size=(3, 1))], 1)


def _centre(T):
    return -T[:, :3].T @ T[:, 3]


def test_turns_keep_the_centre_and_shifts_move_along_the_optical_axis():
    T = _pose()
    conf = SearchConfig(yaw=15.0, pitch=10.0, shift=0.25)
    starts = perturbations(T, depth=8.0, conf=conf)
    assert len(starts) == conf.size() == 7 and starts[0][1] == "reference" and np.allclose(starts[0][0], T)
    view = T[2, :3]  # the optical axis in world coordinates
    for P, label in starts[1:]:
        assert np.allclose(P[:, :3] @ P[:, :3].T, np.eye(3))
        t, R = pose_errors(P, T)
        if label.startswith(("yaw", "pitch")):
            assert t == pytest.approx(0, abs=1e-9) and R == pytest.approx(15.0 if label.startswith("yaw") else 10.0)
            axis = 1 if label.startswith("yaw") else 0  # the camera's own y (down) or x (right) axis
            assert np.allclose(P[axis, :3], T[axis, :3])
        else:
            assert R == pytest.approx(0, abs=1e-6) and t == pytest.approx(2.0)
            move = _centre(P) - _centre(T)
            assert np.allclose(move, (2.0 if label.startswith("forward") else -2.0) * view)


def test_a_search_without_perturbations_is_the_reference_poses():
    assert [label for _, label in perturbations(_pose(), 1.0, SearchConfig(yaw=0, pitch=0, shift=0))] == ["reference"]
    with pytest.raises(ValueError, match="at least 1"):
        SearchConfig(keep=0).validate()


def test_coarse_poses_within_the_merge_tolerance_share_a_basin():
    T = _pose(1)
    conf = SearchConfig(merge_t=0.02, merge_R=1.0)
    depth = 10.0  # 2 % of it: 0.2 units
    moved = T.copy()
    moved[:, 3] -= T[:, :3] @ np.array([0.15, 0.0, 0.0])  # the centre moved by 0.15
    assert same_basin(T, moved, depth, conf)
    moved[:, 3] -= T[:, :3] @ np.array([0.1, 0.0, 0.0])  # 0.25 in all
    assert not same_basin(T, moved, depth, conf)
    turned = perturbations(T, depth, SearchConfig(yaw=0.8, pitch=0, shift=0))[1][0]
    assert same_basin(T, turned, depth, conf)
    turned = perturbations(T, depth, SearchConfig(yaw=1.5, pitch=0, shift=0))[1][0]
    assert not same_basin(T, turned, depth, conf)
    assert same_basin(T, T, depth, SearchConfig(merge_t=0, merge_R=0))  # 0 tolerances: equal poses only


def _screened(evidence, confidence):
    """A start after the coarse screening (``None`` evidence: it did not converge)."""
    return SimpleNamespace(refined=None if evidence is None else np.eye(3, 4), evidence=evidence or {},
                           confidence=confidence)


def test_the_screening_ranks_by_cost_among_starts_that_keep_the_points_in_view():
    # the screening of virtual_gallery's query rgb_00491 (pixloc benchmark search), three of its 28 starts:
    # the most confident ends 14 deg from the truth, the cheapest 3 deg (and converges when refined)
    evidence = [{"cost": 0.079, "valid": 0.9, "weighted_inliers": 0.0},   # pitch -10: 0.18 m, 14.3 deg
                {"cost": 0.076, "valid": 0.8, "weighted_inliers": 0.0},   # yaw -15: 0.14 m, 3.2 deg
                {"cost": 0.050, "valid": 0.3, "weighted_inliers": 0.0}]   # most points out of view
    confidence = [0.564, 0.010, 0.9]
    results = [_screened(e, c) for e, c in zip(evidence, confidence)]
    assert screening_order(results, SearchConfig()) == [1, 0, 2]
    assert screening_order(results, SearchConfig(min_valid=0.0)) == [2, 1, 0]
    assert screening_order(results, SearchConfig(rank="confidence")) == [2, 0, 1]
    assert screening_order(results, SearchConfig(), skip=[1]) == [0, 2]  # the always-refined starts
    assert screening_order(results + [_screened(None, 0.0)], SearchConfig()) == [1, 0, 2]  # not converged
    tied = [_screened(evidence[0], 0.2), _screened(evidence[0], 0.6)]
    assert screening_order(tied, SearchConfig()) == [1, 0]  # equal costs: the more confident
    with pytest.raises(ValueError, match="rank must be one of cost, confidence"):
        SearchConfig(rank="inliers").validate()
    with pytest.raises(ValueError, match="min_valid"):
        SearchConfig(min_valid=1.5).validate()

