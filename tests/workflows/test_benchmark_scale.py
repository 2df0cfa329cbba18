"""S2's goal lines (``workflows.benchmarks.scale.city_goals``): per prior, time and memory against the
smallest city, and recall at (25 cm, 2 deg): at least 70 % and within 5 points across sizes."""

from workflows.benchmarks.scale import city_goals


def _row(prior, s, rss_mib, recall):
    return {"prior": prior, "s_per_query": s, "peak_rss": rss_mib * 2**20,
            "recall": {"recall@0.25m,2.0deg": recall, "recall@1.0m,5.0deg": recall}}


def test_each_prior_is_judged_against_its_own_smallest_city():
    # the photo cities of 208, 832 and 2,548 images, 2026-12-05: top1 and sift (their recalls)
    rows = [_row("top1", 1.90, 1609, 0.625), _row("sift", 1.67, 1668, 0.8125),
            _row("top1", 1.90, 1657, 0.625), _row("sift", 1.80, 1778, 0.8125),
            _row("top1", 2.00, 1661, 0.469), _row("sift", 1.95, 2031, 0.78125)]
    top1, sift = city_goals(rows)
    assert top1.startswith("top1: time at most 1.05 x") and "peak RSS at most 1661 MiB (goal 2048): met" in top1
    assert top1.endswith("recall at (25 cm, 2 deg) 46.9 to 62.5 % (goal at least 70 % and within 5 points): not met")
    assert sift.startswith("sift: time at most 1.17 x the smallest city's (goal 1.2x): met")
    assert sift.endswith("78.1 to 81.2 % (goal at least 70 % and within 5 points): met")
    # a city without a recall (no query localized) counts as 0 %, never NaN
    assert "0.0 to 0.0 %" in city_goals([_row("sift", 1.0, 100, None)])[0]
