import pytest

from pipeline.scene import CameraRecord
from pipeline.data.training_data import PairConfig, PairDataset, synthetic_scene
from workflows.cli import main
from workflows.evaluate_model import evaluate_models, markdown, paired, paired_markdown, sign_test

CAMERA = CameraRecord("PINHOLE", 128, 96, (100.0, 100.0, 64.0, 48.0))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return synthetic_scene(tmp_path_factory.mktemp("syn"), 6, CAMERA, num_references=12, queries_per_condition=2)


def test_models_are_compared_from_the_same_priors(scene):
    exact = PairDataset([("syn", scene)], PairConfig(max_size=128, num_points=128, init_range=(1.0, 1.0)))
    far = PairDataset([("syn", scene)], PairConfig(max_size=128, num_points=128, init_range=(0.5, 0.5)))
    errors = {}
    results = evaluate_models(["photometric", "lite0-imagenet"], [("exact", exact), ("far", far)], 3, num_iters=5,
                              pair_errors=errors)
    assert set(results) == {"prior", "photometric", "lite0-imagenet"}
    prior = results["prior"]
    assert prior["exact"]["median_t"] < 1e-4 and prior["exact"]["recall@0.05m,2.0deg"] == 1.0
    assert prior["far"]["median_t"] > prior["exact"]["median_t"] and prior["all"]["count"] == 6
    for model in ("photometric", "lite0-imagenet"):
        assert results[model]["all"]["count"] == 6 and results[model]["all"]["seconds_per_pair"] > 0
    table = markdown(results)
    assert table.count("\n") == 2 + 3 * 3 and "recall@0.25m,2.0deg" in table
    # Pair by pair: the same pairs, counted consistently with the summaries.
    assert {m: {d: len(e) for d, e in per.items()} for m, per in errors.items()} == {
        m: {"exact": 3, "far": 3} for m in ("prior", "photometric", "lite0-imagenet")}
    comparison = paired(errors, "photometric")
    assert set(comparison) == {"lite0-imagenet"}
    for data in ("exact", "far", "all"):
        c = comparison["lite0-imagenet"][data]
        assert c["pairs"] == (6 if data == "all" else 3) and c["closer"] + c["farther"] <= c["pairs"]
        for key in ("0.05m,2.0deg", "0.25m,2.0deg"):
            a, b = results["photometric"][data][f"recall@{key}"], results["lite0-imagenet"][data][f"recall@{key}"]
            assert c[f"gained@{key}"] - c[f"lost@{key}"] == round((b - a) * c["pairs"])
    assert paired_markdown(comparison, "photometric").count("\n| lite0-imagenet |") == 3


def test_sign_test():
    assert sign_test(0, 0) == 1.0 and sign_test(3, 3) == 1.0
    assert sign_test(10, 0) == pytest.approx(2 / 1024)  # 10 wins out of 10: p = 2 * 0.5^10
    assert sign_test(2, 8) == sign_test(8, 2) == pytest.approx(2 * (1 + 10 + 45) / 1024)
    errors = {"a": {"d": [(0.10, 1.0), (0.20, 1.0), (0.30, 3.0)]}, "b": {"d": [(0.01, 1.0), (0.2005, 1.0), (0.5, 1.0)]}}
    c = paired(errors, "a")["b"]["d"]
    assert (c["closer"], c["farther"]) == (1, 1)  # 0.5 mm is a tie
    assert (c["gained@0.25m,2.0deg"], c["lost@0.25m,2.0deg"]) == (0, 0)  # pair 3: out for both (R, then t)
    assert (c["gained@0.05m,2.0deg"], c["lost@0.05m,2.0deg"]) == (1, 0)
    no_pose = paired({"a": {"d": [(0.1, 1.0)]}, "b": {"d": [(float("nan"), float("nan"))]}}, "a")["b"]["d"]
    assert (no_pose["closer"], no_pose["farther"], no_pose["lost@0.25m,2.0deg"]) == (0, 1, 1)


def test_missing_held_out_data_is_a_clear_error(tmp_path, capsys):
    assert main(["evaluate-model", "--data-root", str(tmp_path), "--output", str(tmp_path / "o")]) == 2
    assert "Held-out data missing" in capsys.readouterr().err


def test_threads_are_set_before_the_work(tmp_path, capsys):
    import torch
    before = torch.get_num_threads()
    try:
        assert main(["evaluate-model", "--threads", "1", "--data-root", str(tmp_path),
                     "--output", str(tmp_path / "o")]) == 2
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
