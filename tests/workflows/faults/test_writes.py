"""Fault catalogue, class 4: writes that survive a full disk, and files we wrote that were damaged
since. Every output goes through ``pipeline.textfiles.write_atomic``; job.json and shard files
are read by readers that name their file and line."""

import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.localization.results import read_records
from pipeline.textfiles import InputError
from workflows.localize import plan_localization, run_sync

from .conftest import ROOT


def _snapshot(folder):
    return {p.relative_to(folder): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_a_write_that_fails_leaves_the_previous_files_whole_and_no_temporaries(cli_run):
    """Before: with the disk full, poses.txt or failed.txt was left at 0 bytes beside a complete
    records.jsonl, and *.tmp files stayed. Here the operating system refuses writes past a file
    size (RLIMIT_FSIZE), as a full disk refuses them, while the run is redone (--overwrite)."""
    import os
    before = _snapshot(cli_run.output)
    limit = len(before[next(p for p in before if p.name == "records.jsonl")]) // 2  # any shard or record file is larger

    def small_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    out = subprocess.run([sys.executable, "-m", "workflows.cli", *map(str, cli_run.args), "--overwrite"],
                         capture_output=True, text=True, preexec_fn=small_files,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 2 and "File too large" in out.stderr
    after = _snapshot(cli_run.output)
    assert not [p for p in after if "tmp" in p.name]
    for name in ("records.jsonl", "poses.txt", "failed.txt", "job.json"):  # whole: the old bytes
        assert after[Path(name)] == before[Path(name)], name
    for path in after:  # and any record file there is complete
        if path.suffix == ".jsonl":
            read_records(cli_run.output / path)
    # the next run completes it
    assert subprocess.run([sys.executable, "-m", "workflows.cli", *map(str, cli_run.args)], capture_output=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}).returncode == 0


def test_a_folder_that_is_not_ours_is_refused(stairs, tmp_path):
    """Before: a foreign poses.txt or records.jsonl in an output folder without job.json was overwritten."""
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "poses.txt").write_text("theirs\n")
    with pytest.raises(ValueError, match="holds files that no pixloc run wrote there \\(poses.txt\\)"):
        plan_localization(stairs.job, stairs.queries[:1], tmp_path / "out")
    with pytest.raises(ValueError, match="no pixloc run"):
        plan_localization(stairs.job, stairs.queries[:1], tmp_path / "out", overwrite=True)
    assert (tmp_path / "out" / "poses.txt").read_text() == "theirs\n"


@pytest.mark.parametrize("damage", ["truncated", "wrong shape"])
def test_a_damaged_job_file_is_named_and_overwrite_gets_past_it(stairs, tmp_path, damage):
    """Before: 'Unterminated string ... (char 282)' or KeyError: 'features', and --overwrite did
    not get past it."""
    run_sync(plan_localization(stairs.job, stairs.queries[:1], tmp_path / "out"))
    job = tmp_path / "out" / "job.json"
    job.write_text(job.read_text()[:120] if damage == "truncated" else "[1, 2]")
    words = r"job.json:\d+: job file is not valid JSON" if damage == "truncated" else "should hold a JSON dict"
    with pytest.raises(InputError, match=words + ".*--overwrite"):
        plan_localization(stairs.job, stairs.queries[:1], tmp_path / "out")
    records = run_sync(plan_localization(stairs.job, stairs.queries[:1], tmp_path / "out", overwrite=True))
    assert records[0]["references"]


@pytest.mark.parametrize("damage", ["truncated", "foreign"])
def test_a_damaged_shard_file_is_run_again(stairs, tmp_path, damage, caplog):
    """Before: "Expecting ',' delimiter" or KeyError: 'name', without the file."""
    queries = stairs.queries[:2]
    run_sync(plan_localization(stairs.job, queries, tmp_path / "out", shard_size=2))
    shard = tmp_path / "out" / "shards" / "shard-00000.jsonl"
    shard.write_text(shard.read_text()[:150] if damage == "truncated" else '{"other": 1}\n')
    plan = plan_localization(stairs.job, queries, tmp_path / "out")
    assert "shard-00000.jsonl:1: records file" in caplog.text and plan.counts()["to_run"] == 2
    records = run_sync(plan)
    assert [r["name"] for r in records] == [q.name for q in queries]
    assert [r["name"] for r in read_records(shard)] == [q.name for q in queries]
