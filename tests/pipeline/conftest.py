import pytest

from pipeline.mapping.readers.colmap import read_colmap


@pytest.fixture(scope="session")
def maupertuis(shared):
    root = shared / "data" / "maupertuis"
    return read_colmap(root / "reconstruction", root / "images")
