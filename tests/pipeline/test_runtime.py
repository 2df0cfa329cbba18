import os
import subprocess
import sys

CODE = "from pipeline.runtime import restore_malloc_thresholds as r; print(r(), r())"


def run(**env):
    base = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", CODE], env={**base, **env}, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_malloc_thresholds_are_restored_only_under_a_trim_threshold():
    # Dask's nannies set MALLOC_TRIM_THRESHOLD_=65536; glibc then stops adapting its mmap threshold
    assert run(MALLOC_TRIM_THRESHOLD_="65536") == ["True", "True"]  # set once per process (cached)
    assert run() == ["False", "False"]  # glibc's dynamic thresholds are untouched
    assert run(MALLOC_TRIM_THRESHOLD_="65536", MALLOC_MMAP_THRESHOLD_="131072") == ["False", "False"]  # user's choice
