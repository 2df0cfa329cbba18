import subprocess
import sys

import pixloc


def run(*args):
    return subprocess.run([sys.executable, "-m", "workflows.cli", *args], capture_output=True, text=True)


def test_version_and_help():
    out = run("--version")
    assert out.returncode == 0 and out.stdout.strip() == f"pixloc {pixloc.__version__}"
    out = run("--help")
    assert out.returncode == 0 and "benchmark" in out.stdout


def test_lm_benchmark_prints_both_rates():
    out = run("benchmark", "lm", "--problems", "2", "--points", "200", "--channels", "16", "--iters", "2",
              "--repeats", "1")
    assert out.returncode == 0, out.stderr
    row = out.stdout.strip().splitlines()[-1].split()
    assert row[:2] == ["2", "200"] and float(row[2]) > 0 and float(row[3]) > 0 and row[4].endswith("x")


def test_presets_set_the_paper_settings(tmp_path):
    import argparse

    from workflows import presets
    from workflows.cli_localize import add_arguments
    assert {"7scenes", "cambridge", "aachen", "robotcar", "cmu", "colmap", "kapture"} <= set(presets.available())
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["list", "q.txt", "--store", "m.zarr", "--output", "o", "--preset", "aachen", "--iters", "7"])
    presets.apply(args, presets.load("aachen"), args._parser_defaults)
    assert (args.num_dbs, args.prior, args.retrieval_k) == (3, "average", 50)
    assert args.iters == 7  # an explicit option wins over the preset
    assert presets.load("robotcar")["retrieval"]["same_tag"] == "camera"
    assert presets.load("cambridge")["localizer"]["average_observations"] is True
    # refinement mode from hloc logs takes the preset's from_poses settings (official run_Aachen.py)
    args = p.parse_args(["list", "q.txt", "--store", "m.zarr", "--output", "o", "--prior", "hloc"])
    presets.apply(args, presets.load("aachen"), args._parser_defaults)
    assert (args.num_dbs, args.iters, args.min_points, args.point_selection, args.levels, args.scales,
            args.average_observations, args.prior) == (5, 50, 100, "inliers", [0, 1], [1], True, "hloc")
