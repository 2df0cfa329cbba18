"""Self-supervised pairs of photos: the query is the photo's plane seen from a known camera, so the
true pose and every correspondence are exact; night changes and occluders alter the looks alone."""

import numpy as np
import pytest
import torch

from pipeline.data import photo_pairs
from pipeline.data.photo_pairs import PhotoPairConfig, PhotoPairs
from pipeline.data.training_data import PairConfig
from pixloc.training import reprojection_px


@pytest.fixture(scope="module")
def photos(shared):
    root = shared / "data"
    found = sorted((root / "robotcar_daynight").glob("db*.jpg"))[:2] + sorted(
        (root / "sacre_coeur" / "mapping").glob("*.jpg"))[:2]
    if len(found) < 4:
        pytest.skip("the shared RobotCar and Sacre Coeur photos are absent")
    return found


def sample_at(image, p):
    """(C, N) bilinear values of a (1, C, H, W) image at (N, 2) pixel coordinates (centres at integers)."""
    size = torch.tensor(image.shape[-1:-3:-1], dtype=torch.float32)
    grid = (p / (size - 1) * 2 - 1)[None, :, None].float()
    return torch.nn.functional.grid_sample(image, grid, align_corners=True)[0, :, :, 0]


def test_points_land_on_the_same_pixels_of_both_images(photos, monkeypatch):
    # without the changes of looks, the query at the true pose shows the reference's colours
    monkeypatch.setattr(photo_pairs, "night_change", lambda x, rng: x)
    monkeypatch.setattr(photo_pairs, "day_change", lambda x, rng: x)
    data = PhotoPairs(photos, PairConfig(), PhotoPairConfig(occluders=0))
    rng = np.random.default_rng(3)
    for _ in range(6):
        b = data.sample(rng)
        p_ref, v_ref = b.camera_ref.cam2image(b.p3d_ref)
        p_q, v_q = b.camera_query.cam2image(b.query_from_ref_gt.transform(b.p3d_ref))
        m = (b.mask_points & v_ref & v_q)[0]
        assert m.sum() >= 50
        same = (sample_at(b.image_ref, p_ref[0][m]) - sample_at(b.image_query, p_q[0][m])).abs().mean()
        shuffled = (sample_at(b.image_ref, p_ref[0][m])
                    - sample_at(b.image_query, p_q[0][m][torch.randperm(int(m.sum()))])).abs().mean()
        assert same < 0.03 and shuffled > 4 * same, (float(same), float(shuffled))


def test_pairs_are_the_same_for_the_same_generator_and_start_off_the_truth(photos):
    data = PhotoPairs(photos, PairConfig(init_range=(0.5, 1.0)))
    a, b = data.fixed(4, seed=5), PhotoPairs(photos, PairConfig(init_range=(0.5, 1.0))).fixed(4, seed=5)
    for x, y in zip(a, b):
        assert torch.equal(x.image_query, y.image_query) and torch.equal(x.p3d_ref, y.p3d_ref)
    errors = [float(reprojection_px(x.query_from_ref_init, x)) for x in a]
    assert all(e > 0 for e in errors) and max(errors) > 1, errors
    # exactly at the truth when the initial pose is drawn at the end of the range
    x = data.pair(0, np.random.default_rng(0), init_fraction=1.0)
    assert float(reprojection_px(x.query_from_ref_init, x)) < 1e-3


def test_night_change_darkens_and_occluders_cover_part_of_the_image():
    rng = np.random.default_rng(0)
    image = rng.uniform(0.3, 0.9, (120, 160, 3)).astype(np.float32)
    night = [photo_pairs.night_change(image, np.random.default_rng(k)) for k in range(5)]
    assert all(n.mean() < 0.8 * image.mean() and n.shape == image.shape for n in night)
    covered = photo_pairs.occlude(image, np.random.default_rng(1), np.zeros_like(image))
    share = np.mean(np.any(covered != image, axis=2))
    assert 0.02 < share < 0.5, share
