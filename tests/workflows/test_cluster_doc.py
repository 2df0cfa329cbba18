"""docs/cluster.md's hand-started cluster, run as written: a `dask scheduler` and `dask worker`
processes started by its commands, then its `build-map` and `localize` lines given the scheduler
file; the held-out query is localized on those workers."""

import json
import os
import re
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from workflows.process_cluster import wait_for

ROOT = Path(__file__).resolve().parents[2]


def doc_commands():
    text = (ROOT / "docs" / "cluster.md").read_text()
    block = text.split("<!-- cluster-example")[1].split("```bash\n", 1)[1].split("```", 1)[0]
    return [line for line in block.splitlines() if line.strip()]


def test_the_cluster_docs_commands_localize_on_a_hand_started_cluster(shared, tmp_path):
    bin_dir = Path(sys.executable).parent
    if not (bin_dir / "dask").exists():
        pytest.skip(f"no dask command next to {sys.executable}")
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "OMP_NUM_THREADS": "1"}
    (tmp_path / "cluster").mkdir()
    background, results = [], []
    try:
        for line in doc_commands():
            line = line.replace("../shared", str(shared))
            if line.endswith("&"):  # the scheduler and the workers: left running
                background.append(subprocess.Popen(shlex.split(line[:-1]), cwd=tmp_path, env=env,
                                                   stderr=subprocess.DEVNULL, start_new_session=True))
                if "scheduler" in line.split()[1]:
                    wait_for((tmp_path / "cluster" / "scheduler.json").exists, 60)
                continue
            results.append(subprocess.run(shlex.split(line), cwd=tmp_path, env=env, capture_output=True, text=True,
                                          timeout=900))
            assert results[-1].returncode == 0, results[-1].stderr[-3000:]
    finally:
        for proc in background:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(30)
    build, localize = results
    assert "features: 7/7 images (100 %)" in build.stderr  # 8 images, one held out
    assert re.search(r"1 query \(1 run in [\d.]+ s, 0 reused\): 1 refined", localize.stdout), localize.stdout
    record = json.loads((tmp_path / "cluster" / "out" / "records.jsonl").read_text().splitlines()[0])
    assert record["name"] == "0003.jpg" and record["success"]
