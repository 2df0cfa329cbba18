"""Fault catalogue, class 3: results that follow the map they came from. job.json records the
store's fingerprint; a half-built store is refused; a finished run has exactly one record per
query; priors and ground truth are matched by the full relative name (``pipeline.textfiles``)."""

import argparse
import dataclasses

import numpy as np
import pytest

from pipeline.mapping.build import build_map
from pipeline.mapping.depth import rgbd_scene
from pipeline.store.feature_groups import feature_key
from pipeline.mapping.readers.rgbd import read_7scenes
from pipeline.localization.priors import OtherPipeline
from pipeline.localization.retrieval import PairsFile
from pipeline.localization.results import read_records
from pipeline.store.layout import PENDING, StoreError, open_store, unconsolidate
from pipeline.textfiles import InputError
from workflows.cli_localize import ground_truth
from workflows.localize import plan_localization, run_sync

from .conftest import FCONF


def _poses_file(path, queries, first=1):
    """A poses file of these queries' ground truth (name qw qx qy qz tx ty tz)."""
    from pipeline.scene import rotmat_to_qvec
    lines = []
    for q in queries:
        T = q.cam_from_world_gt
        lines.append(" ".join([q.name, *map(str, rotmat_to_qvec(T[:, :3])), *map(str, T[:, 3])]))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_rerun_against_a_rebuilt_map_is_refused(stairs, tmp_path):
    """Before: after the store was rebuilt from other sequences, a rerun said '3 of 3 already done:
    nothing to do' and kept records that name references no longer in the map."""
    job = stairs.copy(tmp_path)
    run_sync(plan_localization(job, stairs.queries[:2], tmp_path / "out"))
    other = rgbd_scene(read_7scenes(stairs.root, [1, 4]), method="frames", stride=24)
    build_map(other, job.store, FCONF, overwrite=True)
    with pytest.raises(ValueError, match="results against another map"):
        plan_localization(job, stairs.queries[:2], tmp_path / "out")
    records = run_sync(plan_localization(job, stairs.queries[:2], tmp_path / "out", overwrite=True))
    names = {im.name for im in other.images}
    assert all(set(r["references"]) <= names for r in records)


def test_a_store_with_pending_images_is_refused_unless_allowed(stairs, tmp_path):
    """Before: a localize run started while build-map was writing gave 3, 1 or 5 refined depending
    on timing, with no warning."""
    job = stairs.copy(tmp_path)
    root = open_store(job.store, mode="r+")
    group = root[f"features/{feature_key(FCONF)}"]
    unconsolidate(group)
    group["status"][2] = PENDING
    with pytest.raises(StoreError, match="1 map images are not built yet.*--allow-partial-map"):
        plan_localization(job, stairs.queries[:1], tmp_path / "out")
    records = run_sync(plan_localization(job, stairs.queries[:1], tmp_path / "out", allow_partial_map=True))
    name = str(root["images/name"][2])
    assert name not in records[0]["references"]


def test_a_query_lost_from_its_shard_file_is_run_again(stairs, tmp_path):
    """Before: a shard file cut to its first line, then a rerun printed '1 failures retried', yet
    the query was in none of records.jsonl, poses.txt, failed.txt (23 of 24 records, rc 0)."""
    queries = stairs.queries[:2]
    run_sync(plan_localization(stairs.job, queries, tmp_path / "out", shard_size=2))
    shard = tmp_path / "out" / "shards" / "shard-00000.jsonl"
    shard.write_text(shard.read_text().splitlines()[0] + "\n")
    plan = plan_localization(stairs.job, queries, tmp_path / "out")
    assert plan.counts()["to_run"] == 1
    records = run_sync(plan)
    assert [r["name"] for r in records] == [q.name for q in queries]
    assert [r["name"] for r in read_records(tmp_path / "out" / "records.jsonl")] == [q.name for q in queries]
    assert [r["name"] for r in read_records(shard)] == [q.name for q in queries]


def test_ground_truth_is_matched_by_the_full_name(stairs, tmp_path):
    """Before: with ground truth for sequence 4 only, sequence-1 queries were scored against
    sequence-4 poses (by bare file name), with no warning."""
    seq4 = [q for q in stairs.queries if q.name.startswith("seq-04")]
    gt = ground_truth(argparse.Namespace(ground_truth=_poses_file(tmp_path / "gt.txt", seq4)), stairs.queries)
    for q in stairs.queries:
        if q.name.startswith("seq-04"):
            np.testing.assert_allclose(gt[q.name], q.cam_from_world_gt, atol=1e-4)  # 7-Scenes R: float32
        else:
            assert gt[q.name] is None
    # a shorter name matches where it is the one that fits: 'frame.jpg' lists, camera names
    short = tmp_path / "short.txt"
    short.write_text((tmp_path / "gt.txt").read_text().replace("seq-04/", "", 1))
    gt = ground_truth(argparse.Namespace(ground_truth=short), seq4)
    assert all(T is not None for T in gt.values())


@pytest.mark.parametrize("damage, words", [
    ("duplicate", ":2: seq-04/frame-000000.color.jpg already has a pose (line 1)"),
    ("zero quaternion", ":1: the quaternion [0.0, 0.0, 0.0, 0.0] is zero"),
    ("short line", ":1: expected 'name qw qx qy qz tx ty tz' (8 fields), got 5"),
    ("nan", ":1: non-finite number"),
])
def test_a_bad_poses_file_is_refused_with_its_line(stairs, tmp_path, damage, words):
    """Before: duplicate names with different poses were accepted (the last one kept), a zero
    quaternion read as the identity, a short line gave 'not enough values to unpack'."""
    seq4 = [q for q in stairs.queries if q.name.startswith("seq-04")][:1]
    path = _poses_file(tmp_path / "gt.txt", seq4)
    line = path.read_text().split()
    if damage == "duplicate":
        path.write_text(path.read_text() + " ".join(line[:4] + ["0.5"] + line[5:]) + "\n")
    elif damage == "zero quaternion":
        path.write_text(" ".join([line[0], "0", "0", "0", "0", *line[5:]]) + "\n")
    elif damage == "short line":
        path.write_text(" ".join(line[:5]) + "\n")
    else:
        path.write_text(" ".join(line[:-1] + ["nan"]) + "\n")
    with pytest.raises(InputError, match="gt.txt" + words.replace("[", r"\[").replace("]", r"\]").replace("(", r"\(")
                       .replace(")", r"\)")):
        ground_truth(argparse.Namespace(ground_truth=path), seq4)


def test_priors_of_another_sequence_are_not_used(stairs, tmp_path):
    """Before: --prior poses gave sequence-1 queries sequence-4 priors and reported them refined."""
    seq1 = [q for q in stairs.queries if q.name.startswith("seq-01")][:1]
    seq4 = [q for q in stairs.queries if q.name.startswith("seq-04")]
    job = dataclasses.replace(stairs.job, prior=OtherPipeline(str(_poses_file(tmp_path / "p.txt", seq4))))
    records = run_sync(plan_localization(job, seq1, tmp_path / "out"))
    assert not records[0]["success"] and "no prior pose" in records[0]["reason"]


def test_one_bad_line_of_a_pairs_file_is_refused_before_the_run(stairs, tmp_path):
    """Before: one bad line of a --pairs file failed every query with 'not enough values to
    unpack', and no file or line."""
    q = stairs.queries[0]
    names = [str(n) for n in open_store(stairs.job.store)["images/name"][:]]
    (tmp_path / "pairs.txt").write_text(f"{q.name} {names[0]}\n{q.name}\n")
    job = dataclasses.replace(stairs.job, retrieval=PairsFile(k=stairs.job.retrieval.k,
                                                              pairs=str(tmp_path / "pairs.txt")))
    with pytest.raises(InputError, match=r"pairs.txt:2: expected 'query reference', got 1 fields"):
        plan_localization(job, [q], tmp_path / "out")
