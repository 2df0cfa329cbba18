"""A rig localized as one body (``pipeline.localization.rigs``) in the demo's generated courtyard, by ``pixloc
localize --rigs --rig-frames``: the frame's pose, each image's pose through its camera, the rig poses file, a
rerun; and an image of a frame that cannot be read."""

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from pipeline.data.rigs import generate_rig_frames, read_rig_frames
from pipeline.data.synthetic import SyntheticConfig, ensure_generated, read_synthetic
from pipeline.evaluate import pose_errors
from pipeline.localization.priors import Top1
from pipeline.localization.refine import Localizer, LocalizerConfig
from pipeline.localization.retrieval import GlobalDescriptors
from pipeline.localization.rigs import Frame, compose, localize_frames
from pipeline.localization.shard import LocalizationJob
from pipeline.models import localization_model
from pipeline.store.reader import open_reader
from workflows.demo import DEMO_CAMERA, DEMO_SEED, demo_map


@pytest.fixture(scope="module")
def rig_scene(tmp_path_factory):
    """The demo's map with 24 references, and the rig at one day and one occluded query pose."""
    work = tmp_path_factory.mktemp("rigs")
    ensure_generated(work / "scene", SyntheticConfig(seed=DEMO_SEED), 24, 1, DEMO_CAMERA, query_spread=0.5)
    store, fconf = demo_map(work, read_synthetic(work / "scene")[0], "pixloc-lite0", DEMO_SEED)
    generate_rig_frames(work / "scene", SyntheticConfig(seed=DEMO_SEED), DEMO_CAMERA, 1,
                        conditions=("day", "occluded"))
    frames = [Frame(key, tuple(qs), tuple(cams), {"condition": c})
              for key, c, qs, cams in read_rig_frames(work / "scene", DEMO_CAMERA)]
    job = LocalizationJob(str(store), fconf, fconf.model, LocalizerConfig(num_dbs=3, num_iters=50),
                          GlobalDescriptors(k=5, same_tag="area"), prior=Top1())
    refiner, digest = localization_model(job.model, job.device)
    reader = open_reader(job.store, job.features, digest)
    return job, reader, Localizer(refiner.extractor, refiner.solvers, reader, job.localizer), frames


def test_an_unreadable_image_of_a_rig_gets_the_bodys_pose(rig_scene):
    job, reader, localizer, frames = rig_scene
    day = frames[0]
    broken = dataclasses.replace(day.queries[2], path=Path("/nonexistent/cam2.png"))
    (result,) = localize_frames(job, reader, localizer, [dataclasses.replace(day, queries=day.queries[:2] + (broken,))])
    assert result.success, result.reason
    lost = result.images[2]
    assert lost.success and "/nonexistent/cam2.png" in lost.notes[-1]
    np.testing.assert_allclose(lost.refined, compose(day.cam_from_body[2], result.pose), atol=1e-9)
    t, R = pose_errors(lost.refined, day.queries[2].cam_from_world_gt)
    assert t < 0.1 and R < 1.0, (t, R)
    assert re.search(r"from [12] starts", lost.notes[-1])


def rig_files(folder: Path, frames) -> list:
    """The query list, rig file and frames file of ``frames`` (one rig, cameras cam0..), as a user writes them; the
    frames file leaves the last image out."""
    from pipeline.scene import rotmat_to_qvec
    lines, frame_lines = [], []
    for f in frames:
        for i, q in enumerate(f.queries):
            c = q.camera
            lines.append(f"{q.name} {c.model} {c.width} {c.height} " + " ".join(f"{v:g}" for v in c.params))
            frame_lines.append(f"{q.name} demo_rig {f.key} cam{i}")
    rig_lines = [f"demo_rig, cam{i}, " + ", ".join(f"{v:.12g}" for v in (*rotmat_to_qvec(C[:, :3]), *C[:, 3]))
                 for i, C in enumerate(frames[0].cam_from_body)]
    frame_lines = frame_lines[:-1]  # the last frame's last image is left out: it is localized alone
    for name, text in (("queries.txt", lines), ("rigs.txt", rig_lines), ("frames.txt", frame_lines)):
        (folder / name).write_text("\n".join(text) + "\n")
    images = frames[0].queries[0].path.parents[3]
    return ["localize", "list", str(folder / "queries.txt"), "--query-images", str(images),
            "--rigs", str(folder / "rigs.txt"), "--rig-frames", str(folder / "frames.txt"), "--sync"]


def test_pixloc_localize_with_rigs(rig_scene, tmp_path, capsys):
    """The user's path: ``pixloc localize --rigs --rig-frames`` writes each image's pose through its camera and
    each frame's rig pose (bodies.txt); a rerun is a no-op; a prior that rigs do not take yet is refused."""
    from pipeline.localization.results import read_records, record_pose
    from pipeline.textfiles import read_poses
    from workflows.cli import main
    job, _, _, frames = rig_scene
    args = rig_files(tmp_path, frames) + ["--store", job.store, "--output", str(tmp_path / "out"),
                                          "--num-dbs", "3", "--retrieval-k", "5",
                                          "--iters", "50"]
    assert main(args) == 0
    records = {r["name"]: r for r in read_records(tmp_path / "out" / "records.jsonl")}
    assert len(records) == 6
    day = frames[0]
    body = records[day.queries[0].name]["body"]
    assert body["key"] == f"demo_rig/{day.key}" and body["success"] and body["images"] == [q.name for q in day.queries]
    t, R = pose_errors(np.asarray(body["pose"]), day.body_gt())
    assert t < 0.1 and R < 1.0, (t, R)
    for q, C in zip(day.queries, day.cam_from_body):
        np.testing.assert_allclose(record_pose(records[q.name]), compose(C, np.asarray(body["pose"])), atol=1e-9)
        rec = records[q.name]
        assert rec["success"] and re.search(r"3 images refined as one pose, from [123] starts", rec["notes"][-1])
    for frame in frames:  # no frame verified wrong
        b = records[frame.queries[0].name]["body"]
        if b["success"]:
            t, R = pose_errors(np.asarray(b["pose"]), frame.body_gt())
            assert t <= 0.25 and R <= 2.0, (frame.key, t, R)
    alone = records[frames[-1].queries[-1].name]
    assert "body" not in alone and not any("refined as one pose" in n for n in alone["notes"])
    assert len(records[frames[-1].queries[0].name]["body"]["images"]) == 2
    rigs = read_poses(tmp_path / "out" / "bodies.txt")
    assert sorted(rigs.poses) == sorted(f"demo_rig/{f.key}" for f in frames)
    capsys.readouterr()
    assert main(args) == 0
    assert "6 of 6 queries already done" in capsys.readouterr().out
    assert main(args[:-4] + ["--output", str(tmp_path / "other"), "--prior", "search"]) == 2
    assert "--prior search is not there yet for rigs and sequences: use --prior top1" in capsys.readouterr().err
    assert main(args[:-4] + ["--output", str(tmp_path / "other"), "--order", "region"]) == 2
    assert "use --order list with --rigs" in capsys.readouterr().err


def test_a_sequences_chunks_are_never_split_across_shards(rig_scene, tmp_path, capsys):
    """``--odometry --chunk``: the plan's shards hold whole chunks; a bad odometry line is named before any work;
    ``--chunk`` alone is refused."""
    from pipeline.textfiles import InputError
    from workflows.cli import main
    from workflows.localize import plan_localization
    job, _, _, frames = rig_scene
    images = [q for f in frames for q in f.queries]
    (tmp_path / "odo.txt").write_text("".join(f"{q.name} 1 0 0 0 0 0 {k}\n" for k, q in enumerate(images)))
    plan = plan_localization(dataclasses.replace(job, odometry=str(tmp_path / "odo.txt"), chunk=4), images,
                             tmp_path / "out", shard_size=3)
    assert [[q.name for q in s] for s in plan.shards] == [[q.name for q in images[:4]], [q.name for q in images[4:]]]
    (tmp_path / "bad.txt").write_text(f"{images[0].name} 1 0 0 0 0 0 0\n{images[1].name} 1 0 0 0 0 0\n")
    with pytest.raises(InputError, match="bad.txt:2: expected 'name qw qx qy qz tx ty tz'"):
        plan_localization(dataclasses.replace(job, odometry=str(tmp_path / "bad.txt"), chunk=4), images,
                          tmp_path / "out2")
    args = rig_files(tmp_path, frames)[:5] + ["--store", job.store, "--output", str(tmp_path / "o3"), "--chunk", "3"]
    assert main(args) == 2
    assert "--chunk cuts an --odometry sequence into chunks: give --odometry too" in capsys.readouterr().err


def test_the_demo_refuses_a_rig_with_another_prior(capsys):
    from workflows.cli import main
    assert main(["demo", "--rig", "--prior", "sift", "--output", "/nonexistent/demo"]) == 2
    assert "--rig --prior sift: a rig frame starts from its images' top-1 references" in capsys.readouterr().err


@pytest.mark.slow
def test_pixloc_demo_rig(tmp_path, capsys):
    """``pixloc demo --rig`` as the README would run it, at the smallest size: its table has both ways per condition
    and no frame verified wrong."""
    import json
    from workflows.cli import main
    assert main(["demo", "--rig", "--references", "18", "--queries-per-condition", "1", "--output",
                 str(tmp_path / "demo")]) == 0
    out = capsys.readouterr().out
    assert "condition=night      rig" in out and "seconds per image" in out
    detail = json.loads((tmp_path / "demo" / "rigs.json").read_text())["frames_detail"]["rig-half"]
    assert len(detail) == 4
    assert not [d for d in detail if d["verified"] and not (d["error_t"] <= 0.25 and d["error_R"] <= 2.0)]


def test_a_bodys_evidence_pools_its_images():
    """The pooled verdict's evidence: contrast weighted by the points in view, fraction in view by points, the body's
    own sigma, the median motion; a sharp image carries a weak one where the body is pinned down."""
    from pipeline.localization.candidates import QueryResult
    from pipeline.localization.rigs import body_evidence
    from pipeline.localization.verify import verify
    common = {"move_t": 0.1, "move_R": 1.0, "last_t": 0.01, "last_R": 0.1, "depth": 5.0, "body_sigma": 0.03}
    sharp = QueryResult("a", True, None, None, num_points=300, evidence={"contrast_3px": 0.2, "valid": 1.0,
                                                                          "sigma": 0.1, **common})
    weak = QueryResult("b", False, None, None, num_points=100, evidence={"contrast_3px": 0.0, "valid": 0.5,
                                                                         "sigma": 0.5, **common})
    ev = body_evidence([sharp, weak], [0, 1])
    assert ev["contrast_3px"] == pytest.approx(0.2 * 300 / 350)
    assert ev["valid"] == pytest.approx(350 / 400)
    assert ev["sigma"] == pytest.approx(0.03) and ev["move_R"] == 1.0
    assert verify(ev)[1] is None
    assert verify(body_evidence([weak], [0]))[1] is not None
