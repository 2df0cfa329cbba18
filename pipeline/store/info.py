"""What a map store says about itself, for the commands that plan a run: its feature groups and
their settings, its images' names, poses and tags, its source. The one place outside the
store's readers and writers that opens a store (``pipeline.store.layout``) for them.
"""

from typing import Dict, List, Optional

import numpy as np

from pipeline.store.feature_groups import feature_key
from pipeline.store.layout import StoreError, image_records, open_store, read, tag_families
from pipeline.store.schema import FeatureConfig

__all__ = ["feature_config", "image_names", "camera_poses", "level_count", "map_source", "map_images",
           "tags_in_map", "check_store", "map_counts", "observations_per_image", "feature_configs"]


def feature_config(store, key: Optional[str] = None) -> FeatureConfig:
    """The settings of the store's feature group ``key`` (default: its only one); StoreError for a
    store without features, with several and no ``key``, or without that one."""
    root = open_store(store)
    groups = sorted(root["features"].group_keys()) if "features" in root else []
    if not groups:
        raise StoreError(f"{store} has no features: run pixloc build-map first.")
    if key is None and len(groups) > 1:
        raise StoreError(f"{store} has several feature groups {groups}: choose one with --features.")
    key = key or groups[0]
    if key not in groups:
        raise StoreError(f"{store} has no feature group {key!r} (it has {groups}).")
    return FeatureConfig.from_dict(dict(root[f"features/{key}"].attrs["config"]))


def level_count(store, conf: FeatureConfig) -> int:
    """The number of levels of the feature group of ``conf``."""
    return len(open_store(store)[f"features/{feature_key(conf)}"].attrs["dims"])


def image_names(store) -> List[str]:
    """The map images' names, in store order."""
    return [str(n) for n in read(open_store(store), "images/name")]


def camera_poses(store) -> np.ndarray:
    """The map images' cam_from_world poses (N, 3, 4), in store order."""
    T = read(open_store(store), "images/cam_from_world")
    return np.concatenate([T[:, :9].reshape(-1, 3, 3), T[:, 9:, None]], 2)


def map_source(store) -> Dict:
    """What the map was built from, as its build recorded it (``{}`` where it did not)."""
    return dict(dict(open_store(store).attrs["pixloc_map"]).get("source", {}))


def map_images(store):
    """The map's images as records (``pipeline.scene.ImageRecord``: paths as recorded at build time)."""
    return image_records(open_store(store))


def tags_in_map(store) -> Dict[str, int]:
    """{tag family: how many map images carry it}."""
    return tag_families(open_store(store))


def check_store(store) -> None:
    """Refuse (StoreError) what is not a map store at ``store``."""
    open_store(store)


def map_counts(store) -> Dict[str, int]:
    """The map's sizes: num_images, num_points, num_observations (as its structure records them)."""
    meta = dict(open_store(store).attrs["pixloc_map"])
    return {k: int(meta[k]) for k in ("num_images", "num_points", "num_observations") if k in meta}


def observations_per_image(store) -> np.ndarray:
    """Each map image's number of observations, in store order."""
    return read(open_store(store), "images/num_obs")


def feature_configs(store) -> List[FeatureConfig]:
    """The settings of every feature group of the store, by group name."""
    root = open_store(store)
    keys = sorted(root["features"].group_keys()) if "features" in root else []
    return [FeatureConfig.from_dict(dict(root[f"features/{k}"].attrs["config"])) for k in keys]
