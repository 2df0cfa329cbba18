"""A rig localized as one body (``pipeline.localization.rigs``) in the demo's generated courtyard: the frame's
pose, each image's pose through its camera, an image that cannot be read, and the rigs benchmark's table."""

import dataclasses
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


def test_a_rig_frame_is_localized_as_one_body(rig_scene):
    job, reader, localizer, frames = rig_scene
    results = localize_frames(job, reader, localizer, frames)
    day = results[0]
    assert day.success, day.reason
    t, R = pose_errors(day.pose, frames[0].body_gt())
    assert t < 0.1 and R < 1.0, (t, R)
    for r, q, C in zip(day.images, frames[0].queries, frames[0].cam_from_body):
        assert r.success and r.name == q.name
        np.testing.assert_allclose(r.refined, compose(C, day.pose), atol=1e-9)
        assert "3 images refined as one pose, from 3 starts" in r.notes[-1]
    for frame, r in zip(frames, results):  # no frame verified wrong
        if r.success:
            t, R = pose_errors(r.pose, frame.body_gt())
            assert t <= 0.25 and R <= 2.0, (frame.key, t, R)


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
    assert "2 starts" in lost.notes[-1]
