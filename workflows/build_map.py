"""The map-building workflow: a plan of stages, run synchronously or on a Dask cluster.

Nothing runs while planning. The structure stage is a single write on the
client; feature extraction is one task per batch of images, annotated with
``resources={"GPU": 1}`` on GPU devices. Tasks are idempotent (a finished
image is skipped), so a killed worker's tasks are simply rerun elsewhere and
an interrupted build resumes with what is missing.
"""

import contextlib
import logging
from dataclasses import dataclass, field
from typing import Dict, List, Optional


from pipeline.mapping.build import ImageResult, extract_features, finish_build, pending_images, write_structure
from pipeline.models import network
from pipeline.mapping.features import FeatureConfig
from pipeline.keypoints import DESCRIPTOR_DIM
from pipeline.scene import Scene
from pipeline.store import location

from . import executor
from pipeline.mapping.readers.sources import describe_source

logger = logging.getLogger(__name__)


@dataclass
class BuildPlan:
    """What a build will do: the scene, the store, the feature config and the task batches."""

    scene: Scene
    store: str  # a folder or a URL (``pipeline.store.location``)
    conf: FeatureConfig
    batches: List[List[int]]
    dims: List[int]
    device: str = "cpu"
    chunk_rows: int = 256
    source: Dict = field(default_factory=dict)
    overwrite: bool = False
    shard_rows: Optional[int] = None
    refused: Dict[str, str] = field(default_factory=dict)  # image name -> why it cannot be used (Scene.check)

    def expected_bytes(self) -> int:
        """Approximate store size before compression: per observation and scale, the features
        (2 bytes per channel in float16, 1 in int8 plus a scale per level, 4 in float32), then a
        confidence and a valid flag per level, and 128 bytes of SIFT descriptor with ``conf.sift``
        (before compression: zeros where no keypoint is near); padding rows are not stored."""
        n_obs = len(self.scene.obs_point)
        dims = self.conf.stored_dims(self.dims)
        width = {"float16": 2, "int8": 1, "float32": 4}[self.conf.dtype]
        conf = 4 if self.conf.dtype == "float32" else 2
        per_level = conf + 1 + (2 if self.conf.dtype == "int8" else 0)
        per_obs = len(self.conf.image_scales) * (width * sum(dims) + per_level * len(dims)) + 8 + 8
        per_obs += DESCRIPTOR_DIM if self.conf.sift else 0
        return n_obs * per_obs + len(self.scene.points) * 28 + len(self.scene.images) * (4 * self.dims[-1] + 200)

    def describe(self) -> str:
        n_obs = len(self.scene.obs_point)
        todo = sum(len(b) for b in self.batches)
        lines = [
            f"map store      {self.store}" + (" (overwritten)" if self.overwrite else ""),
            f"source         {describe_source(self.source) if self.source else '(a scene given by the caller)'}",
            f"features       {self.conf.to_dict()} on {self.device}",
            "stages:",
            f"  1 structure  {len(self.scene.images)} images, {len(self.scene.points)} points, {n_obs} observations",
            f"  2 features   {todo} images to extract in {len(self.batches)} tasks "
            f"({len(self.scene.images) - todo} already done or refused)",
            f"expected size  {self.expected_bytes() / 2**20:.1f} MiB",
        ]
        return "\n".join(lines)


def plan_build(scene: Scene, store, conf: FeatureConfig, *, batch_size: int = 1, device: str = "cpu",
               chunk_rows: int = 256, shard_rows: Optional[int] = None, source: Optional[Dict] = None,
               overwrite: bool = False) -> BuildPlan:
    """Plan a build; images already done in an existing store are not planned again (all are
    with ``overwrite``, which rebuilds the store). Images of ``scene`` that an existing store does
    not have are added to it (a new mapping session, ``pipeline.store.structure.extend_store``): they get
    the indices after the stored ones."""
    if batch_size < 1 or chunk_rows < 1 or (shard_rows is not None and (shard_rows < 1 or shard_rows % chunk_rows)):
        raise ValueError(f"--batch-size and --chunk-rows must be at least 1 and --shard-rows a multiple of "
                         f"--chunk-rows, not {batch_size}, {chunk_rows} and {shard_rows}.")
    store = location.normalize(store)
    problems = scene.check()  # images that cannot be used: write_structure records them as failed
    if location.exists(store) and not overwrite:
        from pipeline.store.info import image_names
        stored = set(image_names(store))
        new = sum(im.name not in stored for im in scene.images)
        todo = pending_images(store, conf) + list(range(len(stored), len(stored) + new))
        todo = sorted(set(todo))
    else:
        todo = [i for i in range(len(scene.images)) if i not in problems]
    batches = [todo[i:i + batch_size] for i in range(0, len(todo), batch_size)]
    dims = list(network(conf.model, "cpu")[0].output_dims)
    return BuildPlan(scene, store, conf, batches, dims, device, chunk_rows, source or {}, overwrite, shard_rows,
                     {scene.images[i].name: reason for i, reason in sorted(problems.items())})


def run_sync(plan: BuildPlan, progress: bool = False) -> List[ImageResult]:
    """Run the plan in this process."""
    batches = prepare_structure(plan)
    results = []
    with _progress(batches, progress) as bar:
        for batch in batches:
            results += extract_features(plan.store, plan.conf, batch, device=plan.device)
            if bar:
                bar.update(len(batch))
    finish_build(plan.store, plan.conf)
    return results


def _progress(batches: List[List[int]], progress: bool):
    if not progress or not batches:
        return contextlib.nullcontext(None)
    from pipeline.progress import Progress
    return Progress(sum(len(b) for b in batches), "features", "image")


def prepare_structure(plan: BuildPlan) -> List[List[int]]:
    """Write (or check) the store structure (refused images whose problem is gone become pending);
    returns the plan's batches less the images finished since planning or refused now."""
    todo = set(write_structure(plan.scene, plan.store, plan.conf, chunk_rows=plan.chunk_rows,
                               shard_rows=plan.shard_rows, source=plan.source, device=plan.device,
                               overwrite=plan.overwrite))
    plan.overwrite = False  # done once: the tasks then resume like any build
    batches = [[i for i in b if i in todo] for b in plan.batches]
    return [b for b in batches if b]


def run_dask(plan: BuildPlan, client, progress: bool = False) -> List[ImageResult]:
    """Run the plan on a dask.distributed client: one task per batch, retried if its worker dies."""
    batches = prepare_structure(plan)
    calls = [(str(plan.store), plan.conf, batch, plan.device) for batch in batches]
    with _progress(batches, progress) as bar:
        done = executor.run_dask(client, extract_features, calls, "features", plan.device,
                                 on_done=(lambda r: bar.update(len(r))) if bar else None)
    finish_build(plan.store, plan.conf)
    return [r for batch_results in done for r in batch_results]
