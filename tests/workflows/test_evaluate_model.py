import pytest

from pipeline.scene import CameraRecord
from pipeline.training_data import PairConfig, PairDataset, synthetic_scene
from workflows.cli import main
from workflows.evaluate_model import evaluate_models, markdown

CAMERA = CameraRecord("PINHOLE", 128, 96, (100.0, 100.0, 64.0, 48.0))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return synthetic_scene(tmp_path_factory.mktemp("syn"), 6, CAMERA, num_references=12, queries_per_condition=2)


def test_models_are_compared_from_the_same_priors(scene):
    exact = PairDataset([("syn", scene)], PairConfig(max_size=128, num_points=128, init_range=(1.0, 1.0)))
    far = PairDataset([("syn", scene)], PairConfig(max_size=128, num_points=128, init_range=(0.5, 0.5)))
    results = evaluate_models(["photometric", "lite0-imagenet"], [("exact", exact), ("far", far)], 3, num_iters=5)
    assert set(results) == {"prior", "photometric", "lite0-imagenet"}
    prior = results["prior"]
    assert prior["exact"]["median_t"] < 1e-4 and prior["exact"]["recall@0.05m,2.0deg"] == 1.0
    assert prior["far"]["median_t"] > prior["exact"]["median_t"] and prior["all"]["count"] == 6
    for model in ("photometric", "lite0-imagenet"):
        assert results[model]["all"]["count"] == 6 and results[model]["all"]["seconds_per_pair"] > 0
    table = markdown(results)
    assert table.count("\n") == 2 + 3 * 3 and "recall@0.25m,2.0deg" in table


def test_missing_held_out_data_is_a_clear_error(tmp_path, capsys):
    assert main(["evaluate-model", "--data-root", str(tmp_path), "--output", str(tmp_path / "o")]) == 2
    assert "Held-out data missing" in capsys.readouterr().err
