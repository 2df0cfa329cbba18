"""The embedded default: a reduced demo (fewer queries) with the shipped model, on Dask workers."""

import numpy as np
import pytest

from pipeline.evaluate import evaluate, pose_errors
from pipeline.results import read_records
from pipeline.synthetic import read_synthetic
from workflows.demo import DEMO_THRESHOLDS, run_demo


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    summary = run_demo(out, queries_per_condition=3, workers=2)
    records = read_records(out / "localization" / "records.jsonl")
    gt = {q.name: q.cam_from_world_gt for q in read_synthetic(out / "scene")[1]}
    return summary, records, gt


@pytest.mark.parametrize("condition", ["day", "dusk", "night", "occluded"])
def test_refinement_beats_its_priors_in_every_condition(demo, condition):
    """The LM refinements themselves (verification aside: every refined pose)."""
    _, records, gt = demo
    refined = [{**r, "success": r["refined"] is not None} for r in records]
    s = evaluate(refined, gt, DEMO_THRESHOLDS, tag_keys=["condition"])[f"condition={condition}"]
    prior, refined = s["prior"], s["refined"]
    assert refined["count"] == prior["count"] == 3
    assert refined["median_t"] < 0.5 * prior["median_t"], (prior, refined)
    assert refined["median_R"] < 0.5 * prior["median_R"], (prior, refined)
    recalls = [k for k in refined if k.startswith("recall@")]
    assert all(refined[k] >= prior[k] for k in recalls)
    assert sum(refined[k] for k in recalls) > sum(prior[k] for k in recalls)


def test_verification_reports_right_poses_and_keeps_priors_otherwise(demo):
    """What the demo reports: verified refinements, else the prior. On this scene (2026-12-01): 10 of 12
    accepted, one of them wrong (an occluded query 3 m off along its viewing direction, see
    docs/verification.md); the reported poses beat the priors overall."""
    summary, records, gt = demo
    accepted = [r for r in records if r["success"]]
    wrong = [r for r in accepted if any(e > lim for e, lim in zip(pose_errors(np.asarray(r["refined"]), gt[r["name"]]),
                                                                    (1.0, 5.0)))]
    print(f"{len(accepted)} of {len(records)} accepted, {len(wrong)} wrong: {[r['name'] for r in wrong]}")
    assert len(accepted) >= 8 and len(wrong) <= 1
    for r in records:
        if not r["success"]:
            assert r["reason"].startswith("rejected: ") and r["refined"] is not None
    reported, prior = summary["all"]["refined"], summary["all"]["prior"]
    assert reported["median_t"] < 0.5 * prior["median_t"] and reported["median_R"] < 0.5 * prior["median_R"]


def test_the_demo_writes_its_report(demo, tmp_path_factory):
    reports = list(tmp_path_factory.getbasetemp().glob("demo*/localization/report.html"))
    assert reports and reports[0].stat().st_size > 50_000  # embedded plots
    assert "<img" in reports[0].read_text()
