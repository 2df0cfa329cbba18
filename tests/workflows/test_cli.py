import subprocess
import sys
from pathlib import Path

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


def _localize_job(*argv, tmp_path=None):
    """The job that ``pixloc localize ... ARGV`` runs (a store's default features)."""
    import argparse

    from pipeline.mapping.features import FeatureConfig
    from pipeline.localization.shard import LocalizationJob
    from workflows.cli_localize import add_arguments, job_settings
    from workflows.options import build
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["list", "q.txt", "--store", "m.zarr", "--output", "o", *argv])
    return build(LocalizationJob, {"store": "m.zarr", "features": FeatureConfig(), "model": "m"}, job_settings(args))


def test_presets_set_the_paper_settings():
    from workflows import presets
    assert {"7scenes", "cambridge", "aachen", "robotcar", "cmu", "colmap", "kapture"} <= set(presets.available())
    job = _localize_job("--preset", "aachen", "--iters", "7")
    assert (job.localizer.num_dbs, job.prior.name, job.retrieval.k) == (3, "average", 50)
    assert job.localizer.num_iters == 7  # an explicit option wins over the preset
    assert presets.load("robotcar")["retrieval"]["same_tag"] == "camera"
    assert presets.load("cambridge")["localizer"]["average_observations"] is True
    # refinement mode from hloc logs takes the preset's from_poses settings (official run_Aachen.py)
    job = _localize_job("--prior", "hloc")
    L = job.localizer
    assert (L.num_dbs, L.num_iters, L.min_points, job.prior.point_selection, job.levels, job.scales,
            L.average_observations, job.prior.name) == (5, 100, 10, "all", None, None, False, "hloc")
    job = _localize_job("--prior", "hloc", "--preset", "aachen")
    L = job.localizer
    assert (L.num_dbs, L.num_iters, L.min_points, job.prior.point_selection, job.levels, job.scales,
            L.average_observations, job.prior.name) == (5, 50, 100, "inliers", (0, 1), (1,), True, "hloc")


def test_explicit_flags_win_even_at_the_builtin_default():
    """Before: a flag equal to the parser default lost to the preset (--prior top1 ran average)."""
    job = _localize_job("--preset", "aachen", "--prior", "top1", "--iters", "100")
    assert (job.prior.name, job.localizer.num_iters) == ("top1", 100)
    job = _localize_job("--preset", "aachen")
    assert (job.prior.name, job.localizer.num_iters) == ("average", 150)
    job = _localize_job()  # no preset: the dataclasses' defaults
    assert (job.prior.name, job.localizer.num_iters, job.localizer.num_dbs, job.localizer.min_track_length,
            job.retrieval.method, job.localizer.verification.enabled) == ("top1", 100, 5, 3, "global", True)
    assert _localize_job("--max-turn", "20").localizer.verification.max_move_R == 20.0  # one Flag line
    job = _localize_job("--no-verify", "--min-confidence", "0.3", "--pairs", "p.txt")
    assert (job.localizer.verification.enabled, job.localizer.verification.min_confidence) == (False, 0.3)
    assert job.retrieval.method == "pairs" and Path(job.retrieval.pairs).is_absolute()


def test_every_preset_works_with_every_prior(tmp_path):
    """Before: --preset aachen --prior poses always failed (point selection 'inliers' needs hloc)."""
    from workflows import presets
    from pipeline.localization.priors import PRIORS
    (tmp_path / "poses.txt").write_text("")
    (tmp_path / "logs.pkl").write_bytes(b"")
    for name in presets.available():
        for prior, entry in PRIORS.items():
            files = [x for flag, f in entry.flags.items() if f.file
                     for x in (flag, str(tmp_path / ("logs.pkl" if "hloc" in flag else "poses.txt")))]
            job = _localize_job("--preset", name, "--prior", prior, *files)
            job.validate()  # raises for a combination that cannot run
    job = _localize_job("--preset", "aachen", "--prior", "poses", "--prior-poses", str(tmp_path / "poses.txt"))
    assert job.prior.name == "poses" and job.levels == (0, 1)
    job = _localize_job("--preset", "aachen", "--prior", "hloc", "--hloc-logs", str(tmp_path / "logs.pkl"))
    assert job.prior.point_selection == "inliers"


def test_an_option_of_another_entry_is_refused():
    """A plug-in's own option given with another entry chosen named both (before: silently unused)."""
    import pytest
    with pytest.raises(ValueError, match="--sift-min-inliers: an option of the prior sift, not of top1"):
        _localize_job("--prior", "top1", "--sift-min-inliers", "20")
    with pytest.raises(ValueError, match="--pairs: an option of the retrieval method pairs, not of global"):
        _localize_job("--retrieval", "global", "--pairs", "p.txt")
    job = _localize_job("--sift-min-inliers", "20")  # the option chooses its prior where none is given
    assert (job.prior.name, job.prior.sift.min_inliers) == ("sift", 20)


def test_one_default_model_everywhere():
    import argparse

    from pipeline.mapping.features import FeatureConfig
    from pixloc.nets.registry import DEFAULT_MODEL
    from workflows import presets
    from workflows.cli_build_map import FLAGS, add_arguments
    from workflows.options import build, given
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["strecha", "x", "--store", "s.zarr"])
    assert DEFAULT_MODEL == "pixloc-lite0" == build(FeatureConfig, given(args, FLAGS)).model == FeatureConfig().model
    assert "(default pixloc-lite0)" in " ".join(p.format_help().split()).replace("- ", "-")
    # the preset's feature settings, then the command line's
    args = p.parse_args(["strecha", "x", "--store", "s.zarr", "--preset", "7scenes", "--pad", "3"])
    conf = build(FeatureConfig, presets.feature_settings(presets.load(args.preset)), given(args, FLAGS))
    assert (conf.resize, conf.image_scales, conf.pad) == (1024, (4, 1), 3)


def test_sift_work_keeps_colmaps_info_lines_off_the_terminal(shared, tmp_path):
    """Before: a build with --sift printed pycolmap's "Creating SIFT CPU feature extractor" (glog INFO) once per
    image from the Dask workers, and the sift prior once per query. The terminal now gets the commands' own
    lines; -v brings COLMAP's back. Also: localize takes build-map's --images for a Bundler bundle's images."""
    import os
    env = {k: v for k, v in os.environ.items() if k != "GLOG_minloglevel"}  # a CLI run in-process sets it

    def run(*args):
        return subprocess.run([sys.executable, "-m", "workflows.cli", *args], capture_output=True, text=True, env=env)
    bare = subprocess.run([sys.executable, "-c", "import numpy as np; from pipeline.keypoints import extract_sift; "
                           "extract_sift(np.random.default_rng(0).integers(0, 255, (120, 160, 3), np.uint8), 160, 50)"],
                          capture_output=True, text=True, env=env)
    assert bare.returncode == 0 and "sift.cc" in bare.stderr  # what an unconfigured process prints
    images = shared / "data" / "bundler_kermit"
    bundle = images / "results.example" / "bundle.out"
    store, held = tmp_path / "kermit.zarr", ["kermit003.jpg", "kermit008.jpg"]
    built = run("build-map", "bundler", str(bundle), "--images", str(images), "--hold-out", *held, "--sift", "1600",
                "--resize", "512", "--store", str(store))  # on the local Dask cluster
    assert built.returncode == 0, built.stderr
    assert "sift.cc" not in built.stderr + built.stdout and "features: 7/7 images" in built.stderr
    assert list((tmp_path / "kermit.work").glob("colmap.INFO.*"))  # the triangulation's COLMAP log, in its file
    levels = run("localize", "bundler", str(bundle), "--query-names", *held, "--store", str(store), "--output",
                 str(tmp_path / "lv"), "--levels", "3")  # before: every query failed with it
    assert levels.returncode == 2 and "--levels [3]: the store's features have levels 0 (finest) to 2" in levels.stderr
    levels = run("localize", "bundler", str(bundle), "--query-names", *held, "--store", str(store), "--output",
                 str(tmp_path / "lv"), "--prior", "sift", "--sift-levels", "1", "3")
    assert levels.returncode == 2 and "--sift-levels [1, 3]: the store's features have levels" in levels.stderr
    for extra in ([], ["-v"]):
        out = tmp_path / f"run{len(extra)}"
        done = run(*extra, "localize", "bundler", str(bundle), "--images", str(images), "--query-names", *held,
                   "--store", str(store), "--prior", "sift", "--sync", "--output", str(out))
        assert done.returncode == 0, done.stderr
        assert ("sift.cc" in done.stderr) == bool(extra)
        assert "2 queries (2 run in" in done.stdout and "0 failed" in done.stdout


def test_numbers_out_of_range_are_refused_before_any_query():
    """Before: --iters 0 failed every query inside the LM ('stack expects a non-empty TensorList'),
    --min-confidence 2 (a percentage meant?) rejected every pose, and --workers 0 waited for ever."""
    import pytest

    from workflows import executor
    for argv, match in ((["--iters", "0"], "num_iters, min_track_length and min_points must be at least 1"),
                        (["--min-track-length", "0"], "must be at least 1"),
                        (["--min-confidence", "2"], r"min_confidence and min_valid must lie in \[0, 1\]"),
                        (["--max-turn", "-1"], "must not be negative")):
        with pytest.raises(ValueError, match=match):
            _localize_job(*argv)
    assert _localize_job("--iters", "1", "--min-confidence", "1").localizer.num_iters == 1
    with pytest.raises(ValueError, match="--workers must be at least 1, not 0"):
        with executor.dask_client(workers=0, dashboard=False):
            pass
    executor.check_device("cpu")  # a CUDA device past this machine's last (none on a CPU build) failed every task
    with pytest.raises(ValueError, match=r"--device cuda:99: this machine has \d+ CUDA device"):
        executor.check_device("cuda:99")
    for argv, said in ((["report", "list", "q.txt", "--output", "o", "--examples", "-2"], "--examples: must be at "
                        "least 0, not -2"), (["demo", "--references", "0"], "--references: must be at least 1, not 0"),
                       (["evaluate-model", "--threads", "x"], "--threads: not a whole number: 'x'")):
        out = run(*argv)  # counts of the commands that no dataclass holds: before, -2 examples were taken
        assert out.returncode == 2 and said in out.stderr, out.stderr
    out = run("--max-image-pixels", "0", "queries", "nowhere")  # 0 was ignored (the default limit stayed)
    assert out.returncode == 2 and "--max-image-pixels: 0 must be a positive number of pixels" in out.stderr
    # build-map's: before, --image-scales 0 or --chunk-rows 0 passed the plan and failed in the work
    # (a division by zero), --batch-size 0 said 'range() arg 3 must not be zero'
    from pipeline.mapping.features import FeatureConfig
    from workflows.build_map import plan_build
    for kwargs, match in ((dict(image_scales=(0,)), "distinct factors of at least 1"),
                          (dict(image_scales=(1, 1)), "distinct factors"),
                          (dict(resize=0), "at least 16 px at the coarsest image scale")):
        with pytest.raises(ValueError, match=match):
            FeatureConfig(**kwargs)
    for kwargs in (dict(batch_size=0), dict(chunk_rows=0), dict(shard_rows=100)):
        with pytest.raises(ValueError, match="must be at least 1 and --shard-rows a multiple of --chunk-rows"):
            plan_build(None, "unused.zarr", FeatureConfig(), **kwargs)


def test_a_file_where_a_folder_belongs_is_refused_before_any_work(shared, tmp_path):
    """--store or --output naming a file (or a folder that holds something else than a store): said first.
    Before: build-map ran its SfM or RGB-D fusion, then failed on the store; localize printed its plan, then
    '[Errno 17] File exists'."""
    kinect = shared / "data" / "rgbd_slambook" / "kinect_room"
    (tmp_path / "afile").write_text("x")
    (tmp_path / "folder").mkdir()
    (tmp_path / "folder" / "notes.txt").write_text("x")
    build = ["build-map", "posetxt", str(kinect), "--intrinsics", "518", "519", "325.5", "253.5", "--depth-ext",
             ".pgm", "--sync", "--work-dir", str(tmp_path / "work")]
    out = run(*build, "--store", str(tmp_path / "afile"))
    assert out.returncode == 2 and f"--store {tmp_path / 'afile'} is a file" in out.stderr, out.stderr
    out = run(*build, "--store", str(tmp_path / "folder"))
    assert out.returncode == 2 and f"{tmp_path / 'folder'} is not a readable zarr group" in out.stderr, out.stderr
    assert not (tmp_path / "work").exists()  # nothing was reconstructed
    (tmp_path / "q.txt").write_text("3.png PINHOLE 640 480 518 519 325.5 253.5\n")
    out = run("localize", "list", str(tmp_path / "q.txt"), "--query-images", str(kinect / "color"), "--store",
              str(shared / "nowhere.zarr"), "--output", str(tmp_path / "afile"))
    assert out.returncode == 2 and f"--output {tmp_path / 'afile'} is a file" in out.stderr, out.stderr
