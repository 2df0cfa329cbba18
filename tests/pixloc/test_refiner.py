import numpy as np
import pytest
import torch

from pixloc.geometry import Camera, Pose
from pixloc.nets import load_official_checkpoint
from pixloc.refiner import PairBatch


@pytest.fixture(scope="module")
def case(oracle):
    d = np.load(oracle / "refiner_forward.npz")
    t = lambda k: torch.from_numpy(d[k])[None]  # noqa: E731
    batch = PairBatch(t("ref_image"), t("query_image"), Camera(t("ref_camera")), Camera(t("query_camera")),
                      t("points3D_ref"), Pose(t("T_r2q_init")), Pose(t("T_r2q_gt")))
    return d, batch


def test_official_refiner_forward_and_loss(oracle, official_checkpoint, case):
    d, batch = case
    model = load_official_checkpoint(official_checkpoint)
    with torch.no_grad():
        pred = model(batch)
        losses = model.loss(pred, batch)
    assert len(pred["query_from_ref"]) == 3  # coarse, middle, fine
    for i in range(3):
        np.testing.assert_allclose(pred["query_from_ref"][i].data[0].numpy(), d[f"T_r2q_opt_{i}"],
                                   atol=5e-3, rtol=0)
    for key in d.files:
        if key.startswith("loss/"):
            assert float(losses[key[len("loss/"):]][0]) == pytest.approx(float(d[key][0]), abs=0.5), key


@pytest.mark.parametrize("model, params", [
    ("SIMPLE_PINHOLE", [500, 320, 240]), ("PINHOLE", [500, 510, 320, 240]), ("SIMPLE_RADIAL", [500, 320, 240, 0.1]),
    ("RADIAL", [500, 320, 240, 0.1, 0.01]), ("OPENCV", [500, 510, 320, 240, 0.1, 0.01, 1e-3, 2e-3]),
    ("FULL_OPENCV", [500, 510, 320, 240, 0.1, 0.01, 1e-3, 2e-3, 1e-4, 0.02, 1e-3, 1e-4]),
    ("OPENCV_FISHEYE", [500, 510, 320, 240, 0.1, 0.01, 1e-3, 2e-3])])
def test_stacked_batches_keep_each_camera_model(model, params):
    """Before: stack rebuilt cameras from their values alone, so a FISHEYE batch (10 values) came
    back as OPENCV and projected through another distortion."""
    cam = Camera.from_colmap(model, 640, 480, params)[None]
    pose = Pose.from_Rt(torch.eye(3)[None], torch.zeros(1, 3))
    one = PairBatch(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 8), cam, cam, torch.ones(1, 5, 3), pose, pose)
    both = PairBatch.stack([one, one])
    p3d = torch.tensor([[0.3, -0.2, 2.0]])
    for stacked in (both.camera_ref, both.camera_query):
        assert stacked.distortion == cam.distortion and stacked._data.shape == (2, cam._data.shape[-1])
        torch.testing.assert_close(stacked[1].cam2image(p3d)[0], cam[0].cam2image(p3d)[0])
