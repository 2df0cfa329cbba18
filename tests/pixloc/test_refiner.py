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
