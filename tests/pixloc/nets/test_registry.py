import pytest
import torch

from pixloc.nets.registry import CheckpointError
from pixloc.nets.registry import available_models, load_refiner, model_info, save_model, shipped_model_path


def test_saved_model_round_trip(tmp_path):
    """float16 weights: the loaded network's features match the saved one's to float16 precision."""
    ref = load_refiner("lite0-imagenet")
    with torch.no_grad():
        ref.solvers[1].damping.theta.fill_(0.3)
    path = save_model(ref, "lite0", tmp_path / "m.pt", {"steps": 7})
    assert path.stat().st_size < 25 * 2 ** 20
    loaded = load_refiner(str(path))
    assert model_info(str(path)) == {"steps": 7}
    assert torch.equal(loaded.solvers[1].damping.theta, ref.solvers[1].damping.theta)
    image = torch.rand(1, 3, 64, 96, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        a, b = ref.extractor(image), loaded.extractor(image)
    for fa, fb in zip(a["features"], b["features"]):
        assert (fa - fb).abs().max() < 2e-2 * fa.abs().max()


def test_photometric_model_is_the_image():
    ref = load_refiner("photometric")
    assert not list(ref.parameters())[:-3]  # only the three damping vectors
    assert ref.normalize_features is False
    image = torch.rand(1, 3, 32, 48)
    out = ref.extractor(image)["features"]
    assert torch.equal(out[0], image)
    assert out[1].shape[-2:] == (8, 12) and torch.allclose(out[2][0, :, 0, 0], image[0, :, :16, :16].mean((1, 2)))


def test_bad_model_files_are_refused(tmp_path):
    bad = tmp_path / "bad.pt"
    torch.save({"format": "pixloc-at-scale-model", "version": 1, "architecture": "lite0",
                "state": {"extractor.nothing": torch.zeros(1)}}, bad)
    with pytest.raises(CheckpointError, match="does not match its configuration"):
        load_refiner(str(bad))
    with pytest.raises(ValueError, match="Unknown feature model"):
        load_refiner("no-such-model")


def test_the_shipped_model_loads_offline_by_name():
    path = shipped_model_path("pixloc-lite0")
    assert path.is_file() and path.stat().st_size <= 25 * 2 ** 20
    ref = load_refiner("pixloc-lite0")
    info = model_info("pixloc-lite0")
    assert info["steps"] > 0 and info["architecture"] == "lite0"
    assert not {"strecha/Herz-Jesus-P8", "7scenes_stairs"} & set(info["data"])
    untrained = load_refiner("lite0-imagenet").extractor.state_dict()
    assert any(not torch.equal(v, untrained[k]) for k, v in ref.extractor.state_dict().items())
    assert "pixloc-lite0" in available_models()
