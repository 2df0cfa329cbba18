"""Fault catalogue, class 2: stores that cannot lie. A file missing under an image marked done is
that image's failure, named (``pipeline.store.layout.missing_objects``, asked by the reader and by
check-store), never fill values read as data; a store is compared with its scene by names; only a
map store is overwritten; a build locks its store."""

import pytest

from pipeline.mapping.build import build_map, extract_features, write_structure
from pipeline.mapping.depth import rgbd_scene
from pipeline.store.feature_groups import feature_key
from pipeline.mapping.readers.rgbd import read_7scenes
from pipeline.store.layout import StoreError, open_store
from pipeline.store.check import check_store
from workflows.localize import plan_localization, run_sync
from workflows.locks import store_lock

from .conftest import FCONF, pixloc


def _image_files(store, array, index):
    """The shard files of image ``index`` in ``array`` (a path under the store)."""
    root = open_store(store)
    meta = root.attrs["pixloc_map"]
    start = int(root["images/row_start"][index])
    folder = store / array / "c" / str(start // meta["shard_rows"])
    return [folder] if folder.is_file() else sorted(p for p in folder.rglob("*") if p.is_file())


def _reference_of_first_query(stairs, job, tmp_path):
    first = run_sync(plan_localization(job, stairs.queries[:1], tmp_path / "first"))
    names = [str(n) for n in open_store(job.store)["images/name"][:]]
    return first[0]["references"][0], names


def test_every_feature_file_deleted_is_never_read_as_zeros(stairs, tmp_path):
    """Before: deleting every feature shard (11 MB -> 0.4 MB) still printed 'all chunks verified',
    and localize --no-verify reported 4 of 4 refined."""
    job = stairs.copy(tmp_path)
    group = tmp_path / "copy.zarr" / "features" / feature_key(FCONF)
    for f in list(group.glob("s0/*/c/**/*")):
        if f.is_file() and "/pca_" not in str(f):  # every row's files; the bases: test_random_damage
            f.unlink()
    report = check_store(job.store)
    assert not report.ok and report.bad and all("missing" in b.error for b in report.bad)
    assert "missing" in report.summary() and "--repair" in report.summary()
    records = run_sync(plan_localization(stairs.unverified(job), stairs.queries[:3], tmp_path / "out"))
    assert not any(r["success"] for r in records)
    assert all("marked done but" in r["reason"] and "files are missing" in r["reason"] for r in records)


def test_one_image_observation_shard_deleted_fails_the_queries_that_use_it(stairs, tmp_path):
    """Before: the reader returned 3,740 observations of point -1 (numpy's last point), and a
    query using that reference was reported refined."""
    job = stairs.copy(tmp_path)
    ref, names = _reference_of_first_query(stairs, job, tmp_path)
    for f in _image_files(tmp_path / "copy.zarr", "observations/point", names.index(ref)):
        f.unlink()
    report = check_store(job.store)
    assert not report.ok and ref in {n for b in report.bad for n in b.images}
    from pipeline.store import reader as map_reader
    map_reader.forget_readers()
    records = run_sync(plan_localization(stairs.unverified(job), stairs.queries[:2], tmp_path / "out"))
    using = [r for r in records if ref in r["references"]]
    assert using and all(not r["success"] and ref in r["reason"] and "observations/point" in r["reason"]
                         for r in using)


def test_a_shard_replaced_by_a_folder_is_found(stairs, tmp_path):
    """Before: a shard file replaced by a directory verified."""
    job = stairs.copy(tmp_path)
    names = [str(n) for n in open_store(job.store)["images/name"][:]]
    victim = _image_files(tmp_path / "copy.zarr", f"features/{feature_key(FCONF)}/s0/features", 2)[0]
    victim.unlink()
    victim.mkdir()
    report = check_store(job.store)
    assert not report.ok and names[2] in report.bad_images()


def test_check_store_repair_has_the_build_redo_only_the_damaged_image(stairs, tmp_path):
    job = stairs.copy(tmp_path)
    names = [str(n) for n in open_store(job.store)["images/name"][:]]
    _image_files(tmp_path / "copy.zarr", f"features/{feature_key(FCONF)}/s0/valid", 1)[0].unlink()
    out = pixloc("check-store", job.store, "--repair")
    assert out.returncode == 1 and names[1] in out.stdout and "1 images marked pending" in out.stdout
    scene = rgbd_scene(read_7scenes(stairs.root, [2, 3]), method="frames", stride=24)
    results = build_map(scene, job.store, FCONF)
    assert [r.name for r in results if r.status == "done"] == [names[1]]
    assert check_store(job.store).ok


def test_check_store_names_pending_images_of_a_half_built_store(stairs, tmp_path):
    """Before: a half-built store printed 'all chunks verified'."""
    scene = rgbd_scene(read_7scenes(stairs.root, [2, 3]), method="frames", stride=24)
    store = tmp_path / "half.zarr"
    write_structure(scene, store, FCONF)
    extract_features(store, FCONF, [0, 1])
    report = check_store(store)
    pending = report.pending[feature_key(FCONF)]
    assert not report.ok and pending == [im.name for im in scene.images[2:]]
    assert f"{len(pending)} images not built yet" in report.summary() and "build-map" in report.summary()


def test_adding_a_session_whose_images_sort_first(stairs, tmp_path):
    """Before: sequences 2 3, then 1 2 3 4 into the same store extended and committed it, then
    failed with 'holds another map' on this and every rerun (the README's own example)."""
    store = tmp_path / "map.zarr"
    build_map(rgbd_scene(read_7scenes(stairs.root, [2, 3]), method="frames", stride=24), store, FCONF)
    more = rgbd_scene(read_7scenes(stairs.root, [1, 2, 3, 4]), method="frames", stride=24)
    results = build_map(more, store, FCONF)
    assert sorted(r.name for r in results if r.status == "done") == sorted(
        im.name for im in more.images if im.name.startswith(("seq-01", "seq-04")))
    again = build_map(more, store, FCONF)  # a rerun is a no-op
    assert not again or all(r.status == "skipped" for r in again)
    root = open_store(store)
    assert sorted(str(n) for n in root["images/name"][:]) == sorted(im.name for im in more.images)
    assert check_store(store).ok


def test_overwrite_erases_only_a_map_store(stairs, tmp_path):
    """Before: build-map --overwrite erased any folder it was pointed at (rc 0)."""
    folder = tmp_path / "notes"
    (folder / "sub").mkdir(parents=True)
    (folder / "notes.txt").write_text("mine")
    (folder / "sub" / "data.bin").write_bytes(b"\0" * 10)
    scene = rgbd_scene(read_7scenes(stairs.root, [2]), method="frames", stride=24)
    with pytest.raises(StoreError, match="not a PixLoc map store.*notes.txt"):
        build_map(scene, folder, FCONF, overwrite=True)
    assert (folder / "notes.txt").read_text() == "mine" and (folder / "sub" / "data.bin").is_file()
    job = stairs.copy(tmp_path)  # a map store is overwritten as before
    build_map(scene, job.store, FCONF, overwrite=True)
    assert len(open_store(job.store)["images/name"][:]) == len(scene.images)


def test_a_second_build_of_a_store_is_refused_while_the_first_runs(stairs, tmp_path):
    """Before: a second build with --overwrite 7 s into the first killed it (KeyError: 'valid')."""
    store = tmp_path / "map.zarr"
    with store_lock(store):
        out = pixloc("build-map", "7scenes", stairs.root, "--sequences", "2", "--store", store, "--sync",
                     "--overwrite", "--resize", "320")
    assert out.returncode == 2 and "is being built by another pixloc build-map" in out.stderr
    assert not store.exists()
