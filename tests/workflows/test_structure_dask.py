"""The structure stage's shards made by a real Dask cluster of 2 worker processes (one pycolmap thread
each): the same database as in one process with pycolmap's threads on every core (``--sync``)."""

import pycolmap

from pipeline.mapping.structure import Tasks, build_database
from pipeline.mapping.readers.colmap import images_fingerprint
from tests.pipeline.test_structure import PAIRS, build, contents, temple  # noqa: F401 - temple is a fixture
from workflows.executor import Session


def test_two_workers_make_the_same_database_as_one_process(temple, tmp_path):  # noqa: F811
    images, root = temple
    build(images, root, tmp_path / "here", threads=0)  # as --sync: pycolmap's threads on every core
    names = [im.name for im in images]
    files = {f[0]: f for f in images_fingerprint(root, names)["images"]}
    with Session(sync=False, workers=2) as session:
        tasks = Tasks(run=session.run, threads=1, sift_chunk=4, match_chunk=8)
        build_database(tmp_path / "dask" / "database.db", root, names, files, PAIRS, tasks,
                       cameras=[im.camera for im in images], cam_from_world=[im.cam_from_world for im in images])
        workers = {w["id"] for w in session.client.scheduler_info()["workers"].values()}
    assert len(workers) == 2
    assert contents(tmp_path / "dask" / "database.db") == contents(tmp_path / "here" / "database.db")
    with pycolmap.Database.open(tmp_path / "dask" / "database.db") as db:
        assert db.num_images() == 12 and db.num_verified_image_pairs() > 15


def test_a_mapper_for_a_source_that_sfm_does_not_reconstruct_is_refused(shared, tmp_path, capsys):
    from workflows import cli
    argv = ["build-map", "middlebury", str(shared / "data" / "middlebury" / "templeRing"), "--store",
            str(tmp_path / "map.zarr"), "--mapper", "global", "--dry-run"]
    assert cli.main(argv) == 2
    assert ("--mapper global: only an sfm source is reconstructed by SfM; a middlebury source is triangulated "
            "from its known poses") in capsys.readouterr().err
    assert not (tmp_path / "map.zarr").exists()
