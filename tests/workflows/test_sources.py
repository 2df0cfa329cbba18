"""Map sources: a held-out split leaves its images out of the map, and a typo in it is refused."""

import pytest

from workflows.sources import MapSource, describe_source, kept, load_scene


def test_hold_out_names_must_be_images_of_the_source():
    assert kept(["a.jpg", "b.jpg", "c.jpg"], ["b.jpg"]) == [True, False, True]
    with pytest.raises(ValueError, match=r"--hold-out: b\.JPG is not among the source's 3 images"):
        kept(["a.jpg", "b.jpg", "c.jpg"], ["b.JPG"])


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
