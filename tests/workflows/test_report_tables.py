"""What the report's and the terminal's tables show (issue: the user's path, round two)."""

import re

import numpy as np
import pytest

from pipeline.evaluate import evaluate, shown_families
from workflows.cli_localize import format_summary
from workflows.report import accuracy_tables, query_errors, query_table

T = np.concatenate([np.eye(3), np.zeros((3, 1))], 1)


def _moved(dx):
    out = T.copy()
    out[0, 3] = dx
    return out.tolist()


def _records():
    """Four kapture-like queries: each its own camera and timestamp, one split, two sequences; the
    last one rejected although its refinement was right."""
    records = []
    for k in range(4):
        rejected = k == 3
        records.append({"name": f"q{k}.jpg", "success": not rejected, "prior": _moved(1.0), "refined": _moved(0.01),
                        "reason": "rejected: confidence 0.45 < 0.5" if rejected else "", "confidence": 0.45,
                        "references": ["db0.jpg"], "tags": {"camera": f"cam{k}", "timestamp": str(k),
                                                            "split": "query", "sequence": f"seq-{k % 2}"}})
    return records


def test_families_of_one_query_per_value_or_one_value_get_no_table():
    """Before: a kapture run tabulated camera=... and timestamp=... (one query each) and split=query:
    16 rows for 4 queries, and empty plots."""
    records = _records()
    summary = evaluate(records, {r["name"]: T for r in records}, ((0.05, 1.0),))
    assert sorted(shown_families(summary)) == ["sequence"]
    assert sorted(shown_families(summary, group_by=["camera"])) == ["camera"]
    with pytest.raises(ValueError, match=r"--group-by: sequense is not a tag of these queries \(theirs: camera, "
                       r"sequence, split, timestamp\)"):  # before: a typo's table was left out without a word
        shown_families(summary, group_by=["sequence", "sequense"])
    html = accuracy_tables(summary, ((0.05, 1.0),), "m")
    assert "family-camera" not in html and "family-split" not in html and "family-sequence" in html
    assert "<th>sequence</th>" in html and "<th>condition</th>" not in html  # headed by its family
    text = format_summary(summary)
    assert "camera=" not in text and "timestamp=" not in text and "sequence=seq-0" in text


def test_a_rejected_query_shows_its_refined_error():
    """Before: q3 was rejected though its refined pose was 1 cm off; the table showed only the
    prior's error, 1 m, and sorted by a hidden value."""
    records = _records()
    errors = {r["name"]: query_errors(r, T) for r in records}
    table = query_table(records, errors, ((0.05, 1.0),), "m")
    assert "refined t (m)" in table
    row = table[table.index("<td>q3.jpg</td>"):].split("</tr>")[0]
    values = [float(v) for v in re.findall(r"data-v='([0-9.]+)'>", row)]
    assert values[1:4] == [1.0, 0.0, 0.01]  # outcome rank, then error t (the prior's), R, then refined t


def test_the_threshold_tradeoff_counts_right_refinements_kept():
    """Rejections of right poses are what a user tunes the threshold on (before: no such view)."""
    from workflows.report_figures import threshold_tradeoff
    records = []
    for k, (conf, off) in enumerate([(0.9, 0.01), (0.7, 0.01), (0.6, 3.0), (0.3, 0.01), (0.2, 3.0)]):
        records.append({"name": f"q{k}", "refined": _moved(off), "confidence": conf, "success": conf >= 0.5,
                        "prior": _moved(1.0), "reason": ""})
    cs, precision, recall, right = threshold_tradeoff(records, {r["name"]: T for r in records}, (0.25, 2.0))
    assert right == 3
    at = {round(c, 2): (p, r) for c, p, r in zip(cs, precision, recall)}
    assert at[0.0] == (3 / 5, 1.0)  # everything accepted
    assert at[0.5] == (2 / 3, 2 / 3)  # the run's default: one wrong kept, one right rejected
    assert at[0.8] == (1.0, 1 / 3)
    assert np.isnan(at[1.0][0]) and at[1.0][1] == 0.0  # nothing accepted: precision undefined


def test_no_right_refinement_gives_a_note_not_flat_curves():
    """Before: a kapture run whose refinements all missed (0.25 m, 2 deg) drew two curves flat at zero."""
    from workflows.report import threshold_section
    job = {"localizer": {"verification": {"min_confidence": 0.5}}}
    wrong = [{"name": f"q{k}", "refined": _moved(3.0), "confidence": c, "success": c >= 0.5, "prior": _moved(1.0),
              "reason": ""} for k, c in enumerate([0.99, 0.0, 0.0])]
    gt = {r["name"]: T for r in wrong}
    html_text = threshold_section(wrong, gt, (0.25, 2.0), job, "m")
    assert "None of the refined queries with ground truth is within 0.25 m, 2 deg" in html_text
    assert "<img" not in html_text
    right = wrong + [{"name": "q9", "refined": _moved(0.01), "confidence": 0.9, "success": True, "prior": _moved(1.0),
                      "reason": ""}]
    assert "<img" in threshold_section(right, {**gt, "q9": T}, (0.25, 2.0), job, "m")
    assert threshold_section(wrong, {}, (0.25, 2.0), job, "m") == ""


def test_the_evidence_panel_names_things_and_fits():
    """Before: raw keys (contrast_3px, last_R) and references clipped at the panel's edge."""
    from workflows.report_figures import evidence_text
    text = evidence_text({"confidence": 0.45, "num_points": 1234, "timings": {"total": 1.2},
                          "evidence": {"contrast_3px": 0.012, "valid": 0.84, "last_R": 0.05},
                          "references": ["training/gallery_light1_loop1/frames/rgb/camera_0/rgb_00223.jpg"]})
    assert "contrast_3px" not in text and "last_R" not in text
    assert "cost lower than 3 px away  1.2%" in text and "turned at the finest level 0.05 deg" in text
    assert max(len(line) for line in text.splitlines()) <= 48 and "rgb_00223.jpg" in text
