"""A run recorded by an earlier version reruns as a no-op: its job.json (``data/job_schema1_*.json``,
written by commit e5ef749's ``pixloc localize`` of the kinect_room frames, before the job had a
schema version and plug-in settings of their own) reads as the same job."""

import json
import subprocess
import sys

from tests.workflows.test_build_map import KINECT_K, ROOT, build_kinect

DATA = ROOT / "tests" / "workflows" / "data"
# an earlier sift run had no keypoint term nor its gate (schema 3): it is the run of these settings
FLAGS = {"top1": [], "sift": ["--prior", "sift", "--sift-keypoint-weight", "0", "--max-keypoint-chi2", "0",
                              "--sift-min-inliers", "12"]}


def test_a_run_recorded_by_the_earlier_schema_reruns_as_a_no_op(shared, tmp_path):
    kinect = shared / "data" / "rgbd_slambook" / "kinect_room"
    # the map as the recorded runs had it: built with gem, build-map's default descriptor then
    built = build_kinect(kinect, tmp_path / "k.zarr", "--rgbd-points", "frames", "--descriptor", "gem")
    assert built.returncode == 0, built.stderr
    for name, flags in FLAGS.items():
        out = tmp_path / name
        command = [sys.executable, "-m", "workflows.cli", "localize", "posetxt", str(kinect), "--intrinsics",
                   *KINECT_K, "--store", str(tmp_path / "k.zarr"), "--output", str(out), "--sync", *flags]
        first = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
        assert first.returncode == 0, first.stderr
        now = json.loads((out / "job.json").read_text())
        assert now["job"]["schema"] == 3 and now["job"]["prior"]["name"] == name
        text = (DATA / f"job_schema1_{name}.json").read_text()
        earlier = json.loads(text.replace("{STORE}", str(tmp_path / "k.zarr")))
        assert "schema" not in earlier["job"] and earlier["job"]["prior"] == name
        earlier["store"] = now["store"]  # this build's fingerprint: the map is the same, its bytes are new
        (out / "job.json").write_text(json.dumps(earlier))
        again = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
        assert again.returncode == 0, again.stderr
        assert "5 of 5 queries already done" in again.stdout and "nothing to do" in again.stdout, again.stdout
        if name == "sift":  # a setting that differs is still another run, named; so is the new default
            (out / "job.json").write_text(json.dumps(earlier))
            other = subprocess.run(command[:-1] + ["13"], capture_output=True, text=True, cwd=ROOT)
            assert other.returncode != 0
            assert "prior.sift.min_inliers: 13 now, 12 there" in other.stderr, other.stderr
            default = command[:-len(flags)] + ["--prior", "sift", "--sift-min-inliers", "12"]
            other = subprocess.run(default, capture_output=True, text=True, cwd=ROOT)
            assert other.returncode != 0
            assert "prior.keypoint_weight: 1.0 now, 0.0 there" in other.stderr, other.stderr
