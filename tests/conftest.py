"""Shared test options and fixtures.

``--device cuda`` runs the same suite on a GPU; tests marked ``gpu`` are
skipped on CPU. Real data comes from ``$PIXLOC_SHARED`` or ``../shared``
beside the repository; tests that need it skip cleanly without it.
"""

import os
from pathlib import Path

import pytest
import torch

from pipeline.localization.finest import FinestFill
from pipeline.runtime import POISON_ENV
from pixloc.nets.unet import FinestMaps

ROOT = Path(__file__).resolve().parents[1]
# cells of the finest level not decoded hold NaN in every test, in this process and the workers it
# starts: a read that bypassed the decoding fails there, where in a run it would read stale memory
os.environ[POISON_ENV] = "1"
FinestFill.poison = FinestMaps.poison = True

# pytest-xdist's workers share the cores: one worker's torch (and the CLI processes it starts) gets
# its share of them, not all of them each (2 workers x 2 threads on 2 cores ran 13 % slower), unless
# the caller set OMP_NUM_THREADS
_workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _workers > 1 and "OMP_NUM_THREADS" not in os.environ:
    os.environ["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // _workers))
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


def pytest_addoption(parser):
    parser.addoption("--device", default="cpu", help="torch device to run the tests on (cpu, cuda)")


def pytest_collection_modifyitems(config, items):
    if not config.getoption("--device").startswith("cuda"):
        skip = pytest.mark.skip(reason="needs --device cuda")
        for item in items:
            if "gpu" in item.keywords:
                item.add_marker(skip)


@pytest.fixture(scope="session")
def device(request) -> torch.device:
    dev = torch.device(request.config.getoption("--device"))
    if dev.type == "cuda" and not torch.cuda.is_available():
        pytest.skip("CUDA is not available")
    return dev


def shared_dir() -> Path | None:
    path = Path(os.environ.get("PIXLOC_SHARED", ROOT.parent / "shared"))
    return path if path.is_dir() else None


@pytest.fixture(scope="session")
def shared() -> Path:
    path = shared_dir()
    if path is None:
        pytest.skip("shared data not found (set PIXLOC_SHARED or put it at ../shared)")
    return path


@pytest.fixture(scope="session")
def oracle(shared) -> Path:
    path = shared / "oracle"
    if not path.is_dir():
        pytest.skip("oracle fixtures not found in the shared data")
    return path


@pytest.fixture(scope="session")
def official_checkpoint(oracle) -> Path:
    """The official-format checkpoint of the oracle (84 MB: absent where only part of it was copied)."""
    path = oracle / "official_megadepth_random" / "checkpoint_best.tar"
    if not path.is_file():
        pytest.skip("the oracle's official checkpoint is not there")
    return path
