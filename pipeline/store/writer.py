"""The one writer of a map store's feature group: what the map build (``pipeline.mapping.build``)
asks of the store, without its keys. It opens the group of a feature config (created with the
structure by ``create_store`` and ``init_features``), says which images are done, failed (and why)
or pending, gives an image's observed points, writes an image's features (rows first, status last)
or its failure, and consolidates the group when the build is over (``pipeline.store.layout``).
"""

from typing import List, Optional, Tuple

import numpy as np
import zarr

from pipeline.scene import ImageRecord, Scene
from pipeline.store.feature_groups import PCABases, feature_key, init_features, mark_failed, needs_pca, \
    write_image_features
from pipeline.store.layout import (DONE, FAILED, PENDING, consolidate, consolidated, image_records, open_store, read,
                                   store_index, unconsolidate)
from pipeline.store.schema import FeatureConfig, ImageFeatures
from pipeline.store.structure import create_store

__all__ = ["DONE", "FAILED", "PENDING", "FeatureWriter", "create_map", "finish_group", "image_count", "image_states"]


def create_map(path, scene: Scene, **kwargs) -> zarr.Group:
    """The store of ``scene``'s structure (``pipeline.store.structure.create_store``: reused when it
    holds the same scene)."""
    return create_store(path, scene, **kwargs)


class FeatureWriter:
    """The feature group of ``conf`` in the store at ``path``, opened for writing (created when
    it is not there: ``pca`` then holds its bases where ``needs_pca``). Another model's group of
    the same key is refused (``StoreError``)."""

    def __init__(self, path, conf: FeatureConfig, digest: str, dims: List[int], pca: Optional[PCABases] = None):
        self.root = open_store(path, mode="r+")
        self.group = init_features(self.root, conf, digest, dims, pca=pca)
        self.meta = self.root.attrs["pixloc_map"]

    @staticmethod
    def needs_pca(path, conf: FeatureConfig) -> bool:
        """Whether creating the group of ``conf`` needs PCA bases first (``needs_pca``)."""
        return needs_pca(open_store(path), conf)

    def states(self) -> Tuple[np.ndarray, np.ndarray]:
        """Every image's status (PENDING, DONE, FAILED) and reason, in store order."""
        return read(self.group, "status", self.meta), read(self.group, "reason", self.meta).astype(object)

    def state(self, i: int) -> Tuple[int, str]:
        """Image i's status and reason."""
        return int(self.group["status"][i]), str(self.group["reason"][i])

    def open_images(self) -> None:
        """Images are about to be written: readers go back to the per-image arrays meanwhile."""
        status = self.states()[0]
        if not consolidated(self.group, self.meta) or (status != DONE).any():
            unconsolidate(self.group)

    def store_index(self, scene: Scene) -> List[int]:
        """The store's index of each of ``scene``'s images (the store keeps its own order)."""
        return store_index(self.root, scene)

    def images(self) -> List[ImageRecord]:
        return image_records(self.root)

    def points(self) -> np.ndarray:
        """The map's points (N, 3)."""
        return self.root["points/xyz"][:]

    def observed_points(self, i: int) -> np.ndarray:
        """The points image i observes, in its rows' order."""
        start, n = int(self.root["images/row_start"][i]), int(self.root["images/num_obs"][i])
        return self.root["observations/point"][start:start + n]

    def write(self, i: int, feats: ImageFeatures) -> None:
        """Image i's features, then its status done (a crash in between leaves it pending)."""
        write_image_features(self.group, self.root, i, feats)

    def fail(self, i: int, reason: str) -> None:
        mark_failed(self.group, i, reason)

    def retry(self, i: int) -> None:
        """Image i pending again (the problem that failed it is gone)."""
        self.group["status"][i] = PENDING


def image_states(path, conf: FeatureConfig) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """Every image's status and reason in the feature group of ``conf``; None where the store has no
    such group (every image is to be made)."""
    root = open_store(path)
    key = f"features/{feature_key(conf)}"
    if key not in root:
        return None
    meta = root.attrs["pixloc_map"]
    return read(root, f"{key}/status", meta), read(root, f"{key}/reason", meta)


def image_count(path) -> int:
    return int(open_store(path).attrs["pixloc_map"]["num_images"])


def finish_group(path, conf: FeatureConfig) -> None:
    """After a build: consolidate the group's per-image arrays for fast opening, unless they are."""
    root = open_store(path, mode="r+")
    group = root[f"features/{feature_key(conf)}"]
    if not consolidated(group, root.attrs["pixloc_map"]):
        consolidate(root, group)
