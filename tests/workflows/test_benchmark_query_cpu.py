"""``pixloc benchmark query-cpu`` on one query: a row per speed-up, real times, and the exact
speed-ups giving today's pose and recall (the whole run: docs/benchmarks.md, "The CPU query")."""

import json

import pytest

from workflows.cli import main

VARIANTS = ["today", "BatchNorm folded", "channels-last", "split convs, 1x1 by oneDNN", "freed memory reused",
            "cell products", "rival starts, every level", "rival starts, stopped where they join (default)",
            "bfloat16 network"]


@pytest.fixture(scope="module")
def rows(shared, tmp_path_factory):
    work = tmp_path_factory.mktemp("query-cpu")
    assert main(["benchmark", "query-cpu", "--shared", str(shared), "--work", str(work), "--scenes", "kermit",
                 "--limit", "1"]) == 0
    return json.loads((work / "rows.json").read_text())


def test_a_row_per_speed_up_with_real_times(rows):
    assert rows["queries"] == 1
    assert [r["variant"] for r in rows["rows"]] == VARIANTS
    for r in rows["rows"]:
        assert r["cpu_s"] > 0 and r["before_lm_s"] > 0 and r["lm_s"] > 0
        assert r["unmatched"] == 0  # every variant refines the query


def test_the_exact_speed_ups_keep_todays_pose_and_recall(rows):
    today, *exact, bf16 = rows["rows"]
    for r in exact:
        # kermit is in Bundler units: its position differences are a percentage of the scene's scale
        assert r["max_dt_pct"] < 0.01 and r["max_dR"] < 0.01, r
        assert r["recalls"] == today["recalls"]
    assert bf16["max_dR"] < 0.1  # reduced precision: close, not the same


def test_the_search_runs_one_network_pass_per_image_scale_for_all_its_starts(rows):
    assert rows["search"]["passes"] == 2.0  # the store's image scales [4, 1]
    assert rows["search"]["runs"] > 10  # its starts, screened and refined, share those passes
