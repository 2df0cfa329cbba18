"""Map sources: a held-out split leaves its images out of the map, and a typo in it is refused."""

import pytest

from pipeline.mapping.readers.sources import MapSource, describe_source, kept, load_scene


def test_hold_out_names_must_be_images_of_the_source():
    assert kept(["a.jpg", "b.jpg", "c.jpg"], ["b.jpg"]) == [True, False, True]
    with pytest.raises(ValueError, match=r"--hold-out: b\.JPG is not among the source's 3 images"):
        kept(["a.jpg", "b.jpg", "c.jpg"], ["b.JPG"])


def test_query_names_must_be_queries_of_the_source(shared):
    """Before: localize --query-names 0004.jpg nope.jpg localized 0004.jpg and said nothing of the other."""
    from pipeline.mapping.readers.sources import load_queries
    root = shared / "data" / "strecha" / "fountain-P11"
    assert [q.name for q in load_queries("strecha", root, names=["0007.jpg", "0003.jpg"])] == ["0003.jpg", "0007.jpg"]
    with pytest.raises(ValueError, match=r"--query-names: nope\.jpg is not among the source's 11 images"):
        load_queries("strecha", root, names=["0003.jpg", "nope.jpg"])


def test_a_held_out_image_is_not_in_the_map_and_the_source_records_it(shared, tmp_path):
    root = shared / "data" / "maupertuis"
    full = load_scene(MapSource("colmap", root / "reconstruction", root / "images"), tmp_path)
    source = MapSource("colmap", root / "reconstruction", root / "images", hold_out=("03.jpg",))
    held = load_scene(source, tmp_path)
    assert [im.name for im in held.images] == [im.name for im in full.images if im.name != "03.jpg"]
    mine = [i for i, im in enumerate(full.images) if im.name == "03.jpg"][0]
    assert len(held.obs_point) == len(full.obs_point) - int((full.obs_image == mine).sum()) > 0
    assert source.to_dict()["hold_out"] == ["03.jpg"] and "hold_out" not in MapSource("sfm", root).to_dict()
    assert describe_source(source.to_dict()).endswith("hold out ['03.jpg'])")


def test_every_posed_format_is_a_map_source_and_a_query_source(shared):
    """Each format's images come with their poses as ground truth, for a held-out split."""
    import numpy as np

    from pipeline.mapping.readers.sources import SOURCES, PosedFormat, load_queries, map_kinds, query_kinds
    posed = [name for name, entry in SOURCES.items() if issubclass(entry, PosedFormat)]
    assert len(posed) >= 7 and set(posed) <= set(map_kinds()) and set(posed) <= set(query_kinds())
    data = shared / "data"
    cases = {"llff": (data / "beer_capture", None, 71), "middlebury": (data / "middlebury" / "dino", None, 48),
             "bundler": (data / "bundler_kermit" / "results.example" / "bundle.out", None, 9),
             "opensfm": (data / "opensfm_berlin" / "reconstruction_example.json", None, 3)}
    kinect = load_queries("posetxt", data / "rgbd_slambook" / "kinect_room", intrinsics=(518.0, 519.0, 325.5, 253.5))
    assert "posetxt" in query_kinds() and [q.name for q in kinect] == [f"color/{i}.png" for i in range(1, 6)]
    assert all(np.isfinite(q.cam_from_world_gt).all() and q.camera.params[0] == 518.0 for q in kinect)
    for kind, (path, images, count) in cases.items():
        queries = load_queries(kind, path, images)
        assert len(queries) == count, kind
        assert all(q.cam_from_world_gt is not None and np.isfinite(q.cam_from_world_gt).all() for q in queries)
