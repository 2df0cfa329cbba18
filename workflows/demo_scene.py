"""The demo's generated scene and map: its seed, camera and thresholds, and its map store built from the
scene's depth and known poses (``pixloc demo``, ``pixloc benchmark rigs``)."""

import time
from pathlib import Path
from typing import Tuple

from pipeline.descriptors import Grid
from pipeline.mapping.depth import rgbd_scene
from pipeline.mapping.features import FeatureConfig
from pipeline.mapping.readers.sources import Synthetic
from pipeline.scene import CameraRecord

from . import build_map

DEMO_SEED = 7  # the training configs use other seeds
DEMO_CAMERA = CameraRecord("PINHOLE", 320, 240, (250.0, 250.0, 160.0, 120.0))
DEMO_THRESHOLDS = ((0.1, 1.0), (0.25, 2.0), (1.0, 5.0))  # (metres, degrees)
# The references stand on a circle looking outwards, 360 / n degrees apart, with a 65 degree field
# of view: below 18 a facade point is seen by fewer than three of them and the map has no points.
MIN_REFERENCES = 18


def demo_map(output: Path, mapping, model: str, seed: int) -> Tuple[Path, FeatureConfig]:
    """The demo's map store at ``output/map.zarr`` from the generated scene's ``mapping`` views (their depth
    and known poses), built or completed; (its path, its feature settings)."""
    t = time.perf_counter()
    scene = rgbd_scene(mapping, method="frames", stride=8, min_track_length=3)
    fconf = FeatureConfig(model=model, resize=max(DEMO_CAMERA.width, DEMO_CAMERA.height), image_scales=(1,),
                          descriptor=Grid.name)
    store = output / "map.zarr"
    plan = build_map.plan_build(scene, store, fconf, source={"kind": Synthetic.name, "seed": seed})
    todo = sum(len(b) for b in plan.batches)
    build_map.run_sync(plan, progress=True)
    print(f"      {len(scene.images)} images, {len(scene.points)} points in {time.perf_counter() - t:.1f} s"
          + ("" if todo else f" (reused {store}: every image already had its features)"))
    return store, fconf
