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


def _localize_args(*argv):
    import argparse

    from workflows.cli_localize import LOCALIZE_DEFAULTS, add_arguments, resolve
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["list", "q.txt", "--store", "m.zarr", "--output", "o", *argv])
    resolve(args, LOCALIZE_DEFAULTS)
    return args


def test_presets_set_the_paper_settings():
    from workflows import presets
    assert {"7scenes", "cambridge", "aachen", "robotcar", "cmu", "colmap", "kapture"} <= set(presets.available())
    args = _localize_args("--preset", "aachen", "--iters", "7")
    assert (args.num_dbs, args.prior, args.retrieval_k) == (3, "average", 50)
    assert args.iters == 7  # an explicit option wins over the preset
    assert presets.load("robotcar")["retrieval"]["same_tag"] == "camera"
    assert presets.load("cambridge")["localizer"]["average_observations"] is True
    # refinement mode from hloc logs takes the preset's from_poses settings (official run_Aachen.py)
    args = _localize_args("--prior", "hloc")
    assert (args.num_dbs, args.iters, args.min_points, args.point_selection, args.levels, args.scales,
            args.average_observations, args.prior) == (5, 100, 10, "all", None, None, False, "hloc")
    args = _localize_args("--prior", "hloc", "--preset", "aachen")
    assert (args.num_dbs, args.iters, args.min_points, args.point_selection, args.levels, args.scales,
            args.average_observations, args.prior) == (5, 50, 100, "inliers", [0, 1], [1], True, "hloc")


def test_explicit_flags_win_even_at_the_builtin_default():
    """Before: a flag equal to the parser default lost to the preset (--prior top1 ran average)."""
    args = _localize_args("--preset", "aachen", "--prior", "top1", "--iters", "100")
    assert (args.prior, args.iters) == ("top1", 100)
    args = _localize_args("--preset", "aachen")
    assert (args.prior, args.iters) == ("average", 150)
    args = _localize_args()  # no preset: the configs' defaults
    assert (args.prior, args.iters, args.num_dbs, args.min_track_length, args.point_selection) == (
        "top1", 100, 5, 3, "all")


def test_every_preset_works_with_every_prior(tmp_path):
    """Before: --preset aachen --prior poses always failed (point selection 'inliers' needs hloc)."""
    from workflows import presets
    from pipeline.features import FeatureConfig
    from pipeline.localize import LocalizerConfig
    from pipeline.shard import PRIORS, LocalizationJob, RetrievalConfig
    (tmp_path / "poses.txt").write_text("")
    (tmp_path / "logs.pkl").write_bytes(b"")
    for name in presets.available():
        for prior in PRIORS:
            args = _localize_args("--preset", name, "--prior", prior)
            job = LocalizationJob("m.zarr", FeatureConfig(), "m", LocalizerConfig(num_dbs=args.num_dbs),
                                  RetrievalConfig(k=args.retrieval_k), prior=prior,
                                  prior_poses=str(tmp_path / "poses.txt"), hloc_logs=str(tmp_path / "logs.pkl"),
                                  point_selection=args.point_selection)
            job.validate()  # raises for a combination that cannot run
    args = _localize_args("--preset", "aachen", "--prior", "poses")
    assert args.point_selection == "all" and args.levels == [0, 1]


def test_one_default_model_everywhere():
    import argparse

    from pipeline.features import FeatureConfig
    from pixloc.nets.registry import DEFAULT_MODEL
    from workflows.cli_build_map import add_arguments
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["strecha", "x", "--store", "s.zarr"])
    assert DEFAULT_MODEL == "pixloc-lite0" == args.model == FeatureConfig().model
