"""Fault catalogue, class 5: what a user reads. Errors name their file; a dry run computes
nothing; Ctrl-C is one line; summaries say each thing once, in the map's units."""

import re

import pytest

from pipeline.evaluate import recall_label
from pipeline.scene import SceneError

from .conftest import pixloc


def test_localize_takes_ground_truth_and_prints_the_table_once_per_thing(cli_run):
    """Before: localize had no --ground-truth (no accuracy table for a query list), and the summary
    printed '1 rejected: rejected: confidence ...'."""
    assert "rejected: rejected" not in cli_run.stdout
    table = [line for line in cli_run.stdout.splitlines() if line.startswith("all ")]
    # a store built through the library records no source: its distances are 'scene units'
    assert len(table) == 2 and "n=2" in table[1] and "0.25 scene units, 2 deg:" in table[1]


def test_recall_labels_are_in_the_map_units():
    """Before: 'recall@0.0532305m,1.0deg' for a map in SfM units, also with --units."""
    assert recall_label("recall@0.0532305m,1.0deg", "SfM units") == "0.0532 SfM units, 1 deg"


def test_dry_run_of_a_map_to_triangulate_computes_and_writes_nothing(shared, tmp_path):
    """Before: build-map --dry-run of a map from known poses ran SIFT, matching and triangulation
    (3 min 42 s) and wrote the work folder."""
    out = pixloc("build-map", "strecha", shared / "data" / "strecha" / "Herz-Jesus-P8", "--store",
                 tmp_path / "map.zarr", "--dry-run", timeout=60)
    assert out.returncode == 0, out.stderr
    assert "0 reconstruction" in out.stdout and "nothing computed or written" in out.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_interrupt_is_one_line(monkeypatch, capsys):
    """Before: Ctrl-C during a Dask localize printed KeyboardInterrupt/CommClosedError tracebacks."""
    from workflows import cli, cli_localize

    def interrupted(args):
        raise KeyboardInterrupt
    monkeypatch.setattr(cli_localize, "main", interrupted)
    rc = cli.main(["localize", "list", "x.txt", "--store", "s.zarr", "--output", "o"])
    err = capsys.readouterr().err
    assert rc == 130 and err == "pixloc: interrupted; run the same command again to resume\n"


def test_sfm_that_finds_no_initial_pair_says_what_to_try(shared, tmp_path):
    """Before: 'no good initial image pair' and nothing about what to change."""
    from pipeline.mapping.readers.colmap import run_sfm
    images = tmp_path / "images"
    images.mkdir()
    for path in (sorted((shared / "data" / "robotcar_daynight").glob("db*.jpg"))[0],
                 sorted((shared / "data" / "sacre_coeur" / "mapping").iterdir())[0]):
        (images / path.name).write_bytes(path.read_bytes())
    with pytest.raises(SceneError, match="What to try: more images .* '--pairs exhaustive'"):
        run_sfm(images, tmp_path / "work")


def test_ctrl_c_during_a_dask_localize_is_one_line_and_resumable(stairs, tmp_path):
    """Before: KeyboardInterrupt and CommClosedError tracebacks. Ctrl-C reaches the whole process
    group (the client, the nannies and the workers of the local cluster), as from a terminal."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from .conftest import ROOT
    args = ["localize", "7scenes", stairs.root, "--query-sequences", "1", "4", "--store", stairs.job.store,
            "--output", tmp_path / "out", "--workers", "2", "--iters", "400", "--shard-size", "1"]
    # SIGINT as a terminal's: a test run started in the background (``pytest ... &`` from a script) has it
    # ignored, and its children would inherit that and run to the end
    p = subprocess.Popen([sys.executable, "-m", "workflows.cli", *map(str, args)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    head = []
    for line in p.stderr:  # the tasks are running
        head.append(line)
        if "queries to do" in line:
            break
    time.sleep(0.5)
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, "".join(head) + err
    assert "Traceback" not in err and "Error" not in err
    assert err.rstrip().splitlines()[-1] == "pixloc: interrupted; run the same command again to resume"
    out = pixloc(*args[:-4], "--iters", "400", "--shard-size", "1", "--sync")
    assert out.returncode == 0 and "6 queries" in out.stdout


def test_report_counts_say_only_true_things():
    """Before: '(those two keep their prior)' whatever the counts, and failed queries have no prior."""
    from workflows.report import counts_text
    T = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]
    records = [{"name": "a", "success": True, "prior": T, "reason": ""},
               {"name": "b", "success": False, "prior": T, "reason": "rejected: confidence 0.20 < 0.5"},
               {"name": "c", "success": False, "prior": None, "reason": "image file c is empty (0 bytes)"}]
    text = counts_text(records)
    assert text.startswith("3 queries: <b>1 refined</b> and verified, 1 rejected by verification, 1 failed.")
    assert text.endswith("Of the 2 queries without a verified pose, 1 reports its prior and 1 has no pose.")
    assert counts_text(records[:1]) == "1 query: <b>1 refined</b> and verified, 0 rejected by verification, 0 failed."


def test_a_rejection_never_reads_minus_zero_percent():
    """Before: reasons read 'the cost is -0.0% lower'."""
    from pipeline.localization.verify import VerificationConfig, verify
    confidence, reason = verify({"contrast_3px": -0.0001, "valid": 0.9, "last_R": 0.0}, VerificationConfig())
    assert confidence < 0.5 and "-0.0%" not in reason and "the cost is no lower at the pose" in reason


def test_a_query_that_is_also_a_map_image_is_named(stairs, tmp_path):
    """Before: localizing a Strecha scene against its own map retrieved the query itself (prior
    error 0.000) and reported 100 % without a word."""
    from pipeline.queries import QueryRecord
    from workflows.cli_localize import queries_in_map
    map_image = stairs.root / "seq-02" / "frame-000000.color.jpg"
    copy = tmp_path / "renamed.jpg"
    copy.write_bytes(map_image.read_bytes())
    cam = stairs.queries[0].camera
    queries = [QueryRecord("seq-02/frame-000000.color.jpg", map_image, cam),  # the same name
               QueryRecord("renamed.jpg", copy, cam),  # the same bytes
               stairs.queries[0]]  # a real query
    assert queries_in_map(stairs.job.store, queries) == ["seq-02/frame-000000.color.jpg", "renamed.jpg"]


def test_evaluate_and_report_take_the_thresholds_the_run_used(cli_run, tmp_path):
    """Before: the README's 7-Scenes `report` line used outdoor thresholds while localize had
    used the preset's."""
    import argparse
    import json

    from workflows.cli_localize import recorded_job, thresholds_of
    job = json.loads((cli_run.output / "job.json").read_text())
    assert job["thresholds"] == [[0.25, 2.0], [0.5, 5.0], [5.0, 10.0]]  # no preset: the defaults, recorded
    job["thresholds"] = [[0.05, 5.0]]  # as a run with the 7scenes preset records them
    (tmp_path / "job.json").write_text(json.dumps(job))
    none = argparse.Namespace(thresholds=None, preset=None, indoor=False)
    recorded = recorded_job(tmp_path).get("thresholds")
    assert thresholds_of(none, recorded) == ((0.05, 5.0),)
    assert thresholds_of(argparse.Namespace(thresholds=["0.1,1"], preset=None, indoor=False), recorded) == ((0.1, 1.0),)


def test_each_query_is_timed_on_its_own(stairs, tmp_path):
    """Before: the report's 'time (s)' column showed the shard's average (4 queries at 7.00)."""
    import time

    from workflows.localize import plan_localization, run_sync
    t0 = time.perf_counter()
    records = run_sync(plan_localization(stairs.job, stairs.queries[:3], tmp_path / "out", shard_size=3))
    wall = time.perf_counter() - t0
    totals = [r["timings"]["total"] for r in records]
    assert all(t > 0 for t in totals) and len(set(totals)) == 3
    assert sum(totals) <= wall  # shares of one run, not three copies of its average
    for r in records:  # its own work at each scale and its share of the batched LM add up to it
        parts = sum(v for k, v in r["timings"].items() if k != "total")
        assert parts <= r["timings"]["total"] + 1e-9


def test_the_terminal_gets_the_plan_and_the_summary_and_the_log_file_the_rest(cli_run):
    """Before: every run printed a Dask dashboard URL, a one-line `job {...}` dump and INFO lines of
    the libraries; SfM printed 120-130 COLMAP log lines."""
    assert "job {" not in cli_run.stdout and "Dask dashboard" not in cli_run.stdout
    log = (cli_run.output / "pixloc.log").read_text()
    assert "INFO workflows.cli_localize: job {" in log
    assert f"log     {cli_run.output / 'pixloc.log'}" in cli_run.stdout


def test_the_plan_shows_the_source_fields_its_kind_reads():
    """Before: 'depth_scale' and 'rgbd_points: tsdf' were printed for a Strecha map."""
    from pathlib import Path

    from pipeline.mapping.readers.sources import MapSource, describe_source
    assert describe_source(MapSource("strecha", Path("/d/H")).to_dict()) == "strecha /d/H"
    assert describe_source(MapSource("7scenes", Path("/d/s"), sequences=(2, 3)).to_dict()) == \
        "7scenes /d/s (sequences [2, 3], rgbd points tsdf)"


def test_colmap_log_goes_to_the_work_folder(shared, tmp_path):
    """Before: triangulation printed about 100 COLMAP log lines (glog) on the terminal, and nothing
    told how far SIFT and matching were; now each stage counts its images or pairs."""
    out = pixloc("build-map", "strecha", shared / "data" / "strecha" / "Herz-Jesus-P8", "--store",
                 tmp_path / "h.zarr", "--sync", "--resize", "256", "--image-scales", "1",
                 "--hold-out", "0004.jpg", "0005.jpg", "0006.jpg", "0007.jpg", timeout=600)  # 4 images: quicker
    assert out.returncode == 0, out.stderr
    assert "feature_extraction.cc" not in out.stderr
    progress = re.compile(r"(SIFT features|SIFT matching|triangulation|features): (\d+ \w+ to do|\d+/\d+ .*)")
    assert all(progress.fullmatch(line) for line in out.stderr.splitlines()), out.stderr
    assert "SIFT features: 4/4 images (100 %)" in out.stderr and "SIFT matching: 6/6 pairs (100 %)" in out.stderr
    assert len((out.stdout + out.stderr).splitlines()) <= 25
    logs = list((tmp_path / "h.work").glob("colmap.INFO.*"))
    assert logs and "feature_extraction.cc" in logs[0].read_text()
    assert (tmp_path / "h.work" / "build-map.log").is_file()


def test_a_bfloat16_pass_on_a_cpu_without_native_bfloat16_is_warned_about(stairs, tmp_path, monkeypatch, capsys):
    """A user who asks for a bfloat16 network pass on a CPU that only emulates it is told that it may be
    slower; on a CPU with avx512_bf16 or amx_bf16 (the developer machine's) nothing is said. Dry runs in
    this process: first with this CPU's own flags, then with the probe answering as a CPU without them."""
    from pipeline.runtime import native_bfloat16
    from workflows import cli, cli_localize
    args = ["localize", "7scenes", str(stairs.root), "--query-sequences", "1", "--store", str(stairs.job.store),
            "--output", str(tmp_path / "out"), "--dry-run"]
    for precision in ("float32", "bfloat16-fine"):
        assert cli.main([*args, "--network-precision", precision]) == 0
        warned = "has no native bfloat16" in capsys.readouterr().out
        assert warned == (precision != "float32" and native_bfloat16() is False)
    monkeypatch.setattr(cli_localize, "native_bfloat16", lambda: False)
    assert cli.main([*args, "--network-precision", "bfloat16"]) == 0
    assert ("warning: --network-precision bfloat16: this CPU has no native bfloat16 (neither avx512_bf16 nor "
            "amx_bf16 among its flags)") in capsys.readouterr().out
    assert cli.main([*args, "--network-precision", "bfloat16", "--device", "cuda"]) == 0  # a dry run: no CPU pass
    assert "no native bfloat16" not in capsys.readouterr().out


def test_ground_truth_that_misses_queries_is_said(tmp_path, caplog):
    """Before: a --ground-truth file without the queries' names (or empty) left them out of the
    evaluation without a word; now none matched is an error, some missing a warning."""
    import argparse
    import types

    from workflows.cli_localize import ground_truth
    queries = [types.SimpleNamespace(name=n) for n in ("a.jpg", "b.jpg")]
    path = tmp_path / "gt.txt"
    path.write_text("")
    with pytest.raises(ValueError, match=r"no pose for any of the 2 queries \(e\.g\. a\.jpg; the file has 0 poses\)"):
        ground_truth(argparse.Namespace(ground_truth=path), queries)
    path.write_text("a.jpg 1 0 0 0 0 0 0\n")
    gt = ground_truth(argparse.Namespace(ground_truth=path), queries)
    assert gt["a.jpg"] is not None and gt["b.jpg"] is None
    assert "1 of the 2 queries have no pose there and are not evaluated (e.g. b.jpg)" in caplog.text
