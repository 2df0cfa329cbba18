"""Sacre Coeur scenes for the benchmarks: the night photo and three day photos held out, each
localized from retrieval against the oracle's SfM model of the day photos.

The SfM has no metric scale. So that figures in metres and thresholds such as (25 cm, 2 deg) mean
the same as on the other scenes, the model is rescaled so that its median camera-to-point distance
is ``MEDIAN_DISTANCE`` = 10 units: 25 cm then stands for 2.5 % of that distance. (Nothing in the
pipeline depends on the absolute scale: the search's shifts and the verification's moves are in
depths.) The night photo's reference pose is ``tests/data/sacre_coeur_night.json``, made by
``scripts/register_night.py`` (docs/night.md).
"""

import dataclasses
import json
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

from pipeline.exif import exif_camera
from pipeline.mapping.features import FeatureConfig
from pipeline.queries import QueryRecord
from pipeline.mapping.readers.colmap import read_colmap
from pipeline.scene import CameraRecord, Scene

from ..build_map import plan_build, run_sync as build_sync

MEDIAN_DISTANCE = 10.0
REFERENCE = Path(__file__).resolve().parents[2] / "tests" / "data" / "sacre_coeur_night.json"
DAY_QUERIES = ("17295357_9106075285.jpg", "32809961_8274055477.jpg", "44120379_8371960244.jpg")


def night_reference(path: Path = REFERENCE) -> Dict:
    return json.loads(Path(path).read_text())


def scale_factor(path: Path = REFERENCE) -> float:
    """From the oracle SfM's units to units whose median camera-to-point distance is 10."""
    return MEDIAN_DISTANCE / night_reference(path)["median_camera_to_point_distance"]


def _scaled_pose(T: np.ndarray, s: float) -> np.ndarray:
    T = np.array(T, dtype=np.float64)
    T[:, 3] *= s
    return T


def scaled(scene: Scene, s: float) -> Scene:
    """The scene with every length multiplied by ``s``."""
    images = [dataclasses.replace(im, cam_from_world=_scaled_pose(im.cam_from_world, s)) for im in scene.images]
    return Scene(images, scene.points * s, scene.obs_point, scene.obs_image, scene.obs_xy, scene.point_ids)


def night_query(shared: Path, s: float) -> QueryRecord:
    """The night photo, with the intrinsics of its EXIF and its reference pose (scaled by ``s``)."""
    path = shared / "data" / "sacre_coeur" / "query" / "night.jpg"
    ref = night_reference()
    return QueryRecord("night.jpg", path, exif_camera(path).camera, {"condition": "night"},
                       _scaled_pose(np.array(ref["cam_from_world"]), s))


def day_queries(shared: Path) -> Dict[str, CameraRecord]:
    """The oracle's three query images and their intrinsics."""
    cams = {}
    for line in (shared / "oracle" / "queries_with_intrinsics.txt").read_text().splitlines():
        name, model, w, h, *params = line.split()
        cams[name] = CameraRecord(model, int(w), int(h), tuple(float(p) for p in params))
    return cams


def sacre_coeur(shared: Path, work: Path, fconf: FeatureConfig, night: bool = True, day: bool = True
                ) -> List[Tuple[str, Path, List[QueryRecord]]]:
    """(name, store, queries): the night photo against all 10 day photos, and each oracle query
    image against the other 9 (its observations removed from the map)."""
    from .verification import store_complete
    root = shared / "data" / "sacre_coeur"
    s = scale_factor()
    scene = scaled(read_colmap(shared / "oracle" / "sacre_coeur_sfm", root / "mapping"), s)
    parts = []
    if night:
        store = work / "sacre_coeur_scaled.zarr"
        if not store_complete(store, fconf):
            build_sync(plan_build(scene, store, fconf))
        parts.append(("sacre_coeur/night", store, [night_query(shared, s)]))
    if day:
        names = [im.name for im in scene.images]
        for name, camera in day_queries(shared).items():
            store = work / f"sacre_coeur_scaled-{name}.zarr"
            if not store_complete(store, fconf):
                build_sync(plan_build(scene.subset([i for i, n in enumerate(names) if n != name]), store, fconf))
            im = scene.images[names.index(name)]
            parts.append((f"sacre_coeur/{name}", store, [QueryRecord(name, im.path, camera, {"condition": "day"},
                                                                     np.asarray(im.cam_from_world))]))
    return parts
