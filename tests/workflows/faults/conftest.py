"""Fixtures of the fault catalogue: one real 7-Scenes map (RGB-D frames of sequences 2 and 3),
built once per session, that each case copies before damaging it."""

import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.mapping.build import build_map
from pipeline.mapping.depth import rgbd_scene
from pipeline.mapping.features import FeatureConfig
from pipeline.localization.refine import LocalizerConfig
from pipeline.mapping.readers.rgbd import read_7scenes
from pipeline.localization.retrieval import GlobalDescriptors
from pipeline.localization.shard import LocalizationJob
from pipeline.localization.verify import VerificationConfig
from pipeline.mapping.readers.sources import load_queries

ROOT = Path(__file__).resolve().parents[3]
FCONF = FeatureConfig(resize=320, image_scales=(1,))
LCONF = LocalizerConfig(num_dbs=3, num_iters=15)


@dataclasses.dataclass
class Stairs:
    job: LocalizationJob
    queries: list
    root: Path  # the 7-Scenes stairs data

    def copy(self, tmp_path, name="copy.zarr") -> LocalizationJob:
        """The job against a copy of the store (to damage)."""
        shutil.copytree(self.job.store, tmp_path / name)
        from pipeline.store import reader as map_reader
        map_reader.forget_readers()  # as a new process: no reader kept from another case
        return dataclasses.replace(self.job, store=str(tmp_path / name))

    def unverified(self, job=None) -> LocalizationJob:
        """Official PixLoc's reporting: every converged refinement is a success."""
        job = job or self.job
        return dataclasses.replace(job, localizer=dataclasses.replace(
            job.localizer, verification=VerificationConfig(enabled=False)))


@pytest.fixture(scope="session")
def stairs(shared, tmp_path_factory) -> Stairs:
    root = shared / "data" / "7scenes_stairs"
    store = tmp_path_factory.mktemp("fault-catalogue") / "map.zarr"
    build_map(rgbd_scene(read_7scenes(root, [2, 3]), method="frames", stride=24), store, FCONF)
    queries = load_queries("7scenes", root, sequences=(1, 4))
    return Stairs(LocalizationJob(str(store), FCONF, FCONF.model, LCONF, GlobalDescriptors(k=5)), queries, root)


def pixloc(*args, cwd=None, timeout=300, env=None):
    """The command line, as a user runs it (a new process)."""
    return subprocess.run([sys.executable, "-m", "workflows.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout, env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})})


@dataclasses.dataclass
class CliRun:
    args: list  # the localize command's arguments (rerun them to resume or redo)
    output: Path
    stdout: str


@pytest.fixture(scope="session")
def cli_run(stairs, tmp_path_factory) -> CliRun:
    """`pixloc localize` as a user runs it: a query list without ground truth, and --ground-truth."""
    from pipeline.scene import rotmat_to_qvec
    work = tmp_path_factory.mktemp("cli-run")
    queries = [q for q in stairs.queries if q.name.startswith("seq-01")][:2]
    (work / "list.txt").write_text("".join(f"{q.name} PINHOLE 640 480 525 525 320 240\n" for q in queries))
    (work / "gt.txt").write_text("".join(
        " ".join([q.name, *map(str, rotmat_to_qvec(q.cam_from_world_gt[:, :3])), *map(str, q.cam_from_world_gt[:, 3])])
        + "\n" for q in queries))
    args = ["localize", "list", work / "list.txt", "--query-images", stairs.root, "--store", stairs.job.store,
            "--output", work / "out", "--sync", "--iters", "15", "--num-dbs", "3", "--ground-truth", work / "gt.txt"]
    out = pixloc(*args)
    assert out.returncode == 0, out.stderr
    return CliRun(args, work / "out", out.stdout)
