"""The mapping benchmark's pose accuracy after a similarity alignment, and the sequential pairs."""

import numpy as np
import pytest

from pipeline.mapping.image_pairs import PairsConfig, select_pairs, sequential_pairs
from workflows.benchmarks.mapping import align_error


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_align_error_is_zero_up_to_a_similarity_and_measures_what_is_left():
    rng = np.random.default_rng(0)
    known, found = {}, {}
    R_s, s, t_s = _rotation(rng), 0.37, rng.normal(size=3)  # found_from_known: x_f = s R x_k + t
    for k in range(8):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = _rotation(rng), rng.normal(size=3) * 5
        known[f"{k}"] = T
        F = np.eye(4)  # the same camera in the found frame: cam_from_found = cam_from_known @ known_from_found
        F[:3, :3] = T[:3, :3] @ R_s.T
        centre = -T[:3, :3].T @ T[:3, 3]
        F[:3, 3] = -F[:3, :3] @ (s * R_s @ centre + t_s)
        found[f"{k}"] = F
    exact = align_error(known, found)
    assert exact["position_pct"] < 1e-8 and exact["rotation_deg"] < 1e-5
    moved = dict(found)
    for name in ("0", "1", "2", "3", "4"):  # five of eight cameras 1 % of the scale off along x (found units)
        M = moved[name].copy()
        M[:3, 3] -= M[:3, :3] @ np.array([0.01 * s * 5, 0, 0])
        moved[name] = M
    off = align_error(known, moved)
    assert 0.05 < off["position_pct"] < 1.5 and off["rotation_deg"] < 0.5  # the fit turns a little
    assert np.isnan(align_error(known, {"0": found["0"]})["position_pct"])


def test_sequential_pairs_are_colmaps_overlap_and_quadratic_overlap():
    names = [f"{k:02d}.jpg" for k in range(10)]
    pairs = set(sequential_pairs(names[::-1], overlap=3))  # name order, whatever the given order
    expected = {(names[i], names[j]) for i in range(10) for j in {i + 1, i + 2, i + 3, i + 4} if j < 10}
    assert pairs == expected  # next 3, and i + 2**k for k < 3 (1, 2, 4)
    assert set(select_pairs(names, PairsConfig("sequential", overlap=3))) == expected
    with pytest.raises(ValueError, match="needs known poses"):
        select_pairs(names, PairsConfig("spatial"))
