"""The embedded default: a reduced demo (fewer queries) with the shipped model, on Dask workers."""

import pytest

from workflows.demo import run_demo


@pytest.fixture(scope="module")
def summary(tmp_path_factory):
    return run_demo(tmp_path_factory.mktemp("demo"), queries_per_condition=3, workers=2)


@pytest.mark.parametrize("condition", ["day", "dusk", "night", "occluded"])
def test_localization_beats_its_priors_in_every_condition(summary, condition):
    s = summary[f"condition={condition}"]
    prior, refined = s["prior"], s["refined"]
    assert refined["count"] == prior["count"] == 3
    assert refined["median_t"] < 0.5 * prior["median_t"], (prior, refined)
    assert refined["median_R"] < 0.5 * prior["median_R"], (prior, refined)
    recalls = [k for k in refined if k.startswith("recall@")]
    assert all(refined[k] >= prior[k] for k in recalls)
    assert sum(refined[k] for k in recalls) > sum(prior[k] for k in recalls)


def test_the_demo_writes_its_report(summary, tmp_path_factory):
    reports = list(tmp_path_factory.getbasetemp().glob("demo*/localization/report.html"))
    assert reports and reports[0].stat().st_size > 50_000  # embedded plots
    assert "<img" in reports[0].read_text()
