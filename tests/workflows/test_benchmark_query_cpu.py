"""``pixloc benchmark query-cpu`` on one query: a row per speed-up, real times, and the exact
speed-ups giving today's pose and recall (the whole run: docs/benchmarks.md, "The CPU query"); and
``pixloc benchmark query-rate`` on its maps: batching gives the same poses."""

import json

import pytest

from workflows.cli import main

VARIANTS = ["today", "BatchNorm folded", "channels-last", "split convs, 1x1 by oneDNN", "freed memory reused",
            "cell products", "rival starts, every level", "rival starts, stopped where they join",
            "finest level decoded where sampled, without rival starts", "finest level decoded where sampled",
            "LM taps compiled, without rival starts", "LM taps compiled (default)",
            "bfloat16 network", "bfloat16 finest blocks", "bfloat16 finest blocks, without rival starts"]


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("query-cpu")


@pytest.fixture(scope="module")
def rows(shared, work):
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
    today, *exact, bf16, fine, fine_alone = rows["rows"]
    for r in exact:
        # kermit is in Bundler units: its position differences are a percentage of the scene's scale
        assert r["max_dt_pct"] < 0.01 and r["max_dR"] < 0.01, r
        assert r["recalls"] == today["recalls"]
    assert bf16["max_dR"] < 0.1  # reduced precision: close, not the same
    for r in (fine, fine_alone):  # only the finest level in reduced precision: closer still
        assert r["max_dR"] < 0.05 and r["recalls"] == today["recalls"], r


def test_rounds_give_each_variant_its_median_run():
    from workflows.benchmarks.query_cpu import median_run
    rounds = [{"cpu": 3.0, "results": "a"}, {"cpu": 1.0, "results": "b"}, {"cpu": 2.0, "results": "c"}]
    median = median_run(rounds)
    assert median["cpu"] == 2.0 and median["results"] == "c" and median["cpu_rounds"] == [3.0, 1.0, 2.0]


def test_the_search_runs_one_network_pass_per_image_scale_for_all_its_starts(rows):
    assert rows["search"]["passes"] == 2.0  # the store's image scales [4, 1]
    assert rows["search"]["runs"] > 10  # its starts, screened and refined, share those passes


EARLIER = "8975496"  # the code when issue 31 was filed


def _has_commit(rev: str) -> bool:
    import subprocess
    from pathlib import Path
    repo = Path(__file__).resolve().parents[2]
    return subprocess.run(["git", "-C", str(repo), "cat-file", "-e", f"{rev}^{{commit}}"],
                          capture_output=True).returncode == 0


# benchmark tooling (a git archive of an old commit, run apart): slow tier, the default suite's 15 minutes
@pytest.mark.slow
def test_the_earlier_code_runs_the_same_query_in_its_own_process(shared, tmp_path):
    """--earlier-code: the real baseline, the commit's own code on a copy of the same map, its poses
    compared with the default's."""
    if not _has_commit(EARLIER):
        pytest.skip(f"commit {EARLIER} is not in this clone (a shallow one)")
    work = tmp_path / "query-cpu"
    assert main(["benchmark", "query-cpu", "--shared", str(shared), "--work", str(work), "--scenes", "kermit",
                 "--limit", "1", "--variants", "LM taps compiled (default)",
                 "--earlier-code", EARLIER]) == 0
    earlier = json.loads((work / "rows.json").read_text())["earlier"]
    assert earlier["rev"] == EARLIER and earlier["cpu_s"] > 0
    assert earlier["speedups"]["LM taps compiled (default)"] > 0
    assert earlier["unmatched"] == 0 and earlier["max_dR"] < 0.05 and earlier["max_dt_pct"] < 0.05
    assert (work / f"code-{EARLIER}" / "pipeline").is_dir()  # its checkout, beside the maps it copied


def test_query_rate_batches_copies_of_the_queries_and_keeps_their_poses(rows, shared, work, capsys):
    """The GPU goal's command (docs/benchmarks.md, "Queries per second"), on the CPU: the maps of the
    query-cpu run above; 3 copies of its query in batches of 1 and of 3 give the same pose, refined."""
    assert main(["benchmark", "query-rate", "--shared", str(shared), "--work", str(work), "--scenes", "kermit",
                 "--limit", "1", "--device", "cpu", "--copies", "3", "--batches", "1", "3"]) == 0
    out = capsys.readouterr().out
    rate = json.loads((work / "rate.json").read_text())
    assert rate["queries"] == 3 and [r["batch"] for r in rate["rows"]] == [1, 3]
    default = next(r for r in rows["rows"] if r["variant"] == "LM taps compiled (default)")
    for r in rate["rows"]:
        assert r["queries_per_s"] > 0 and r["cpu_s"] > 0
        assert r["unmatched"] == 0 and r["max_dt_pct"] < 0.01 and r["max_dR"] < 0.01, r
        assert r["recalls"] == default["recalls"]  # query-cpu's default, on the same query
    assert f"| 3 | 3 | {rate['rows'][1]['wall_s']:.1f} |" in out and "goal on a GPU: 20" in out
