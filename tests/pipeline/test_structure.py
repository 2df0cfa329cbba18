"""The structure stage in shards (pipeline.mapping.structure): SIFT per chunk of images, matching per
chunk of pairs, assembled into COLMAP's database; a killed or damaged build redoes only what is missing."""

import json

import numpy as np
import pycolmap
import pytest

from pipeline.mapping.image_pairs import PairsConfig
from pipeline.mapping.readers.colmap import images_fingerprint, triangulate_known_poses
from pipeline.mapping.structure import Tasks, build_database, in_process

PAIRS = PairsConfig("spatial", num_neighbors=4)


@pytest.fixture(scope="module")
def temple(shared):
    from pipeline.mapping.readers.middlebury import read_middlebury
    root = shared / "data" / "middlebury" / "templeRing"
    images = read_middlebury(root)[:12]
    return images, images[0].path.parent


class Counting:
    """A ``Tasks.run`` that runs in this process, records each task, and stops (as a killed run
    would) after ``stop_after`` tasks of the stage named ``stop_in``."""

    def __init__(self, stop_in=None, stop_after=0):
        self.calls, self.stop_in, self.stop_after = [], stop_in, stop_after

    def __call__(self, fn, calls, name, on_done=None):
        out = []
        for args in calls:
            if name == self.stop_in and len([c for c in self.calls if c == name]) >= self.stop_after:
                raise KeyboardInterrupt(f"killed during {name}")
            self.calls.append(name)
            out.append(in_process(fn, [args], name, on_done)[0])
        return out


def build(images, root, work, run=in_process, match_chunk=8, threads=1):
    names = [im.name for im in images]
    files = {f[0]: f for f in images_fingerprint(root, names)["images"]}
    work.mkdir(parents=True, exist_ok=True)
    tasks = Tasks(run=run, threads=threads, match_chunk=match_chunk)
    return build_database(work / "database.db", root, names, files, PAIRS, tasks,
                          cameras=[im.camera for im in images], cam_from_world=[im.cam_from_world for im in images])


def contents(path):
    """Everything the mapping reads from a database, by image name."""
    with pycolmap.Database.open(path) as db:
        images = {im.image_id: im.name for im in db.read_all_images()}
        out = {"ids": sorted(images.items())}
        for i, name in images.items():
            out[f"kp {name}"] = db.read_keypoints(i).tobytes()
            out[f"desc {name}"] = np.asarray(db.read_descriptors(i).data).tobytes()
            cam = db.read_camera(i)
            out[f"cam {name}"] = (cam.model.name, cam.width, cam.height, list(cam.params), cam.has_prior_focal_length)
        for pair_id, g in zip(*db.read_two_view_geometries()):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            out[f"tvg {images[a]} {images[b]}"] = (int(g.config), np.asarray(g.inlier_matches).tobytes())
            out[f"matches {images[a]} {images[b]}"] = np.asarray(db.read_matches(a, b)).tobytes()
    return out


def test_a_killed_build_redoes_only_missing_shards_and_assembles_the_same_database(temple, tmp_path, caplog):
    images, root = temple
    used = build(images, root, tmp_path / "whole")
    assert used == [im.name for im in images]
    whole = contents(tmp_path / "whole" / "database.db")
    assert [name for _, name in whole["ids"]] == used  # ids in the order of the names, not of the threads
    assert sum(k.startswith("tvg") for k in whole) == len((tmp_path / "whole" / "pairs.txt").read_text().splitlines())
    assert sum(len(v) > 0 for k, v in whole.items() if k.startswith("matches")) > 20

    # killed during SIFT (after 1 of 6 chunks of 2 images), then during matching (after 2 chunks of pairs)
    work = tmp_path / "resumed"
    with pytest.raises(KeyboardInterrupt):
        build(images, root, work, Counting("sift", 1))
    assert len(list((work / "shards").glob("sift-*.npz"))) == 1 and not (work / "database.db").exists()
    with pytest.raises(KeyboardInterrupt):
        build(images, root, work, Counting("matching", 2))
    assert len(list((work / "shards").glob("matches-*.npz"))) == 2
    run = Counting()
    with caplog.at_level("INFO"):
        build(images, root, work, run)
    made = len(list((work / "shards").glob("matches-*.npz")))
    assert run.calls == ["matching"] * (made - 2)  # no SIFT, and only the pairs' chunks not made yet
    assert "SIFT features: 6 of 6 shards already made" in caplog.text
    assert contents(work / "database.db") == whole

    # a rerun makes nothing; damaged shards are named and made again, to the same database
    run = Counting()
    build(images, root, work, run)
    assert run.calls == []
    sift = sorted((work / "shards").glob("sift-*.npz"))[1]
    sift.write_bytes(sift.read_bytes()[:4096])  # cut short
    npz = sorted((work / "shards").glob("matches-*.npz"))[0]
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF
    npz.write_bytes(bytes(data))
    caplog.clear()
    run = Counting()
    with caplog.at_level("WARNING"):
        build(images, root, work, run)
    assert f"SIFT shard {sift} is damaged" in caplog.text and f"matching shard {npz} is damaged" in caplog.text
    assert run.calls.count("sift") == 1 and "matching" in run.calls
    assert contents(work / "database.db") == whole


def test_a_build_killed_while_mapping_reuses_every_shard(temple, tmp_path):
    """Killed during triangulation: SIFT and matching are all in shards, the model has no marker yet;
    the rerun runs no SIFT or matching task and triangulates the same points."""
    images, root = temple
    run = Counting()
    first = triangulate_known_poses(images, root, tmp_path, pairs=PAIRS, tasks=Tasks(run=run, threads=1))
    assert run.calls.count("sift") == 6 and run.calls.count("matching") >= 1
    (tmp_path / "triangulation.json").unlink()  # as a kill before the model is finished leaves it
    run = Counting()
    again = triangulate_known_poses(images, root, tmp_path, pairs=PAIRS, tasks=Tasks(run=run, threads=1))
    assert run.calls == []
    assert len(again.points) == pytest.approx(len(first.points), rel=0.01) and len(first.points) > 1000
    assert json.loads((tmp_path / "triangulation.json").read_text())["kind"] == "triangulation"


def test_global_sfm_reconstructs_the_temple_within_a_percent_of_its_known_poses(shared, tmp_path):
    """``mapper="global"`` (pycolmap's GLOMAP; the PNGs carry no focal length: the view graph calibrates
    them first): every image registered, the camera centres within 2 % of the scene's scale of the known
    ones after a similarity, and the rotations within a degree."""
    from pipeline.mapping.readers.colmap import run_sfm
    from pipeline.mapping.readers.middlebury import read_middlebury
    from workflows.benchmarks.mapping import align_error
    images = read_middlebury(shared / "data" / "middlebury" / "templeRing")
    root = images[0].path.parent
    scene = run_sfm(root, tmp_path, [im.name for im in images], mapper="global")
    assert len(scene.images) == len(images) and len(scene.points) > 1500
    error = align_error({im.name: im.cam_from_world for im in images},
                        {im.name: im.cam_from_world for im in scene.images})
    assert error["position_pct"] < 2.0 and error["rotation_deg"] < 1.0, error
    assert json.loads((tmp_path / "sfm.json").read_text())["mapper"] == "global"
    with pytest.raises(ValueError, match="Unknown mapper 'glomap'; known: incremental, global, hierarchical"):
        run_sfm(root, tmp_path, [im.name for im in images], mapper="glomap")
