"""Read access to a map store for localization: observations of reference images and their features."""

import functools
import json
import logging
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from pipeline.store import location
from pipeline.store.compression import dequantize_int8, reconstruct
from pipeline.store.schema import FeatureConfig
from pipeline.scene import CameraRecord
from pipeline.store.feature_groups import feature_key, pca_bases
from pipeline.store.layout import (DONE, FAILED, StoreError, StoreReadError, check_feature_group, consolidated,
                                   missing_objects, open_store, stored_dims)
from pipeline.store.layout import read as store_read

logger = logging.getLogger(__name__)


@dataclass
class Observations:
    """M observations of the selected points in the selected reference images.

    point: (M,) point ids; db: (M,) reference image index; rows: (M,) store rows.
    """

    point: np.ndarray
    db: np.ndarray
    rows: np.ndarray


class MapReader:
    """A map store opened for localization with one feature config.

    Refuses a store whose features were made by another model (``digest``)
    or config. Reference blocks (an image's rows at one image scale, every level) are read once and
    cached as stored (int8 codes or float16, principal components), least recently used first out, up
    to ``cache_images`` blocks and ``cache_bytes`` bytes, and decoded to float32 per query for the rows
    it uses: as float32 the cache held 3.5 times the bytes (docs/scaling.md, "S2"). ``stats`` counts
    the blocks read, the cache hits and the bytes read.
    """

    def __init__(self, path, conf: FeatureConfig, digest: Optional[str] = None, cache_images: int = 256,
                 cache_bytes: int = 512 * 2**20, read_threads: int = 16):
        self.path = path  # a folder or a URL (``pipeline.store.location``)
        root = open_store(path)
        meta = root.attrs["pixloc_map"]
        key = f"features/{feature_key(conf)}"
        if key not in root:
            available = sorted(root["features"].group_keys()) if "features" in root else []
            raise StoreError(f"{path} has no features for {conf.to_dict()} (it has: {available or 'none'}).")
        self.group = root[key]
        if not conf.made(self.group.attrs.get("config")):
            check_feature_group(self.group, meta, path)  # a damaged record is named as such
            raise StoreError(f"{path}: features {key} were made with {self.group.attrs.get('config')}.")
        check_feature_group(self.group, meta, path)
        self.dims: List[int] = list(self.group.attrs["dims"])
        self.stored_dims = stored_dims(self.group)
        if digest is not None and self.group.attrs.get("model_digest") != digest:
            raise StoreError(f"{path}: features were made with model {self.group.attrs.get('model_digest')}, "
                             f"not the localizer's {digest}: rebuild the map with this model.")
        self.conf = conf

        def read(group, name):
            try:
                return store_read(group, name, meta)
            except Exception as e:  # a corrupt chunk of the structure: every query needs it  # noqa: BLE001
                raise StoreReadError(f"{path}: array {group[name].path} cannot be read: {type(e).__name__}: {e}"
                                     " (run pixloc check-store)") from None
        self.names = [str(n) for n in read(root, "images/name")]
        self.index = {n: i for i, n in enumerate(self.names)}
        self.cameras = [CameraRecord.from_json(str(c)) for c in read(root, "images/camera")]
        self.tags = [json.loads(str(t)) for t in read(root, "images/tags")]
        T = read(root, "images/cam_from_world")
        self.cam_from_world = np.concatenate([T[:, :9].reshape(-1, 3, 3), T[:, 9:, None]], 2)
        self.row_start = read(root, "images/row_start")
        self.num_obs = read(root, "images/num_obs")
        # a finished build's one-chunk copies (fast to open), else the per-image arrays
        self.static = consolidated(self.group, meta)
        self.status = read(self.group, "status_all" if self.static else "status")
        self.xyz = read(root, "points/xyz")
        self.track_length = read(root, "points/track_length")
        self._root, self._paths = root, None
        self.image_source_id = read(root, "images/source_id")
        self.point_source_id = read(root, "points/source_id")
        self.global_descriptors = read(self.group, "global_all" if self.static else "global")
        self.pca = pca_bases(self.group)  # levels stored as principal components: reconstructed on read
        self._read = read
        self.stats = {"blocks": 0, "hits": 0, "bytes": 0}
        self._blocks: "OrderedDict[Tuple[int, int], Tuple]" = OrderedDict()
        self._cache_limits = (cache_images, cache_bytes)
        self._cached_bytes = 0
        # a query's reference blocks and point rows are read concurrently: against object storage
        # a read is a few round trips, and one at a time they would add up (docs/cluster.md)
        self._read_threads = read_threads
        # each image scale's arrays, opened once (opening one reads its metadata)
        names = ["features", "scales", "confidences", "valid"] if conf.dtype == "int8" else [
            "features", "confidences", "valid"]
        self._block_arrays = [{name: self.group[f"s{k}/{name}"] for name in names}
                              for k in range(len(conf.image_scales))]
        self._leave_out_lost()
        # per-observation arrays read per image on demand, each cached: the points (every query
        # needs them), where they are observed and their SIFT descriptors (the sift prior's)
        per_image = {"point": (root["observations/point"], 4 * cache_images),
                     "xy": (root["observations/xy"], cache_images)}
        if "sift" in self.group:
            per_image["sift"] = (self.group["sift"], cache_images)
        self._rows = {name: functools.lru_cache(maxsize=size)(functools.partial(self._image_rows, array=array))
                      for name, (array, size) in per_image.items()}

    def _leave_out_lost(self) -> None:
        """Descriptors are unit vectors: a done image's zero one is a missing chunk read as fill
        values. Such images are left out of the run, named in the log."""
        lost = np.flatnonzero((self.status == DONE) & ~np.abs(self.global_descriptors).any(1))
        if len(lost):
            logger.error("%s: %d reference images marked done have no global descriptor on disk (%s): left out "
                         "of this run; run pixloc check-store", self.path, len(lost),
                         ", ".join(self.names[i] for i in lost[:3]))
            self.status = self.status.copy()
            self.status[lost] = FAILED

    def _check_present(self, i: int, arrays) -> None:
        """A done image whose rows are not all on disk fails the query that needs it, named; its
        rows are never read as fill values (zeros, point -1)."""
        s = slice(int(self.row_start[i]), int(self.row_start[i] + self.num_obs[i]))
        missing = missing_objects(arrays, s)
        if missing:
            raise StoreReadError(f"map store {self.path}: reference image {self.names[i]} is marked done but "
                                 f"{len(missing)} of its files are missing ({', '.join(missing[:2])}"
                                 f"{' ...' if len(missing) > 2 else ''}): rebuild it (run pixloc check-store)")

    def _image_rows(self, i: int, array) -> np.ndarray:
        """Image i's rows of a per-observation array, its files checked first; read on demand (the
        callers cache them per image)."""
        self._check_present(i, [array])
        try:
            return np.asarray(array[int(self.row_start[i]):int(self.row_start[i] + self.num_obs[i])])
        except Exception as e:  # noqa: BLE001
            raise StoreReadError(f"map store {self.path}: array {array.path} cannot be read for reference "
                                 f"image {self.names[i]}: {type(e).__name__}: {e}") from None

    def image_points(self, i: int) -> np.ndarray:
        """The points observed by image i, in row order (read on demand and cached); a point that the
        map does not hold (attributes and arrays that disagree) fails the query that reads it, named."""
        points = self._rows["point"](int(i))
        if len(points) and (points.min() < 0 or points.max() >= len(self.xyz)):
            raise StoreReadError(f"map store {self.path}: reference image {self.names[i]} observes point "
                                 f"{int(points.max() if points.max() >= len(self.xyz) else points.min())}, but the "
                                 f"map holds points 0-{len(self.xyz) - 1}: a damaged store (run pixloc check-store)")
        return points

    def image_xy(self, i: int) -> np.ndarray:
        """Where image i observes its points (N, 2), COLMAP pixel coordinates, in row order (NaN
        where the source has none: RGB-D maps); read on demand and cached, as ``image_points``."""
        return self._rows["xy"](int(i)).astype(np.float64)

    def sift_descriptors(self, i: int) -> Optional[np.ndarray]:
        """Image i's stored SIFT descriptor per observation ((N, 128) uint8, in row order; zeros where
        no keypoint is near), or None where the map stores none (``FeatureConfig.sift``); cached."""
        return self._rows["sift"](int(i)) if "sift" in self._rows else None

    def image_path(self, i: int) -> Path:
        """Image i's file, as recorded at build time."""
        if self._paths is None:
            self._paths = [Path(str(p)) for p in self._read(self._root, "images/path")]
        return self._paths[i]

    def refresh(self) -> None:
        """Re-read which images are usable (a build may have finished more since); nothing to do
        for a consolidated store (a build that changes it rewrites the group's attributes, and
        ``open_reader`` then opens it again)."""
        if not self.static:
            self.status = self._read(self.group, "status")
            self.global_descriptors = self._read(self.group, "global")
            self._leave_out_lost()

    def usable(self, i: int) -> bool:
        return int(self.status[i]) == DONE

    def observations(self, dbs: List[int], min_track_length: int,
                     selected: Optional[np.ndarray] = None) -> Observations:
        """Every observation, in ``dbs``, of the points they see with track length >= min;
        only the (point, image) pairs of ``selected`` (K, 2) when given (hloc PnP inliers)."""
        self._concurrently(self.image_points, dbs)
        rows = [np.arange(self.row_start[i], self.row_start[i] + self.num_obs[i]) for i in dbs]
        db = np.concatenate([np.full(len(r), i) for r, i in zip(rows, dbs)]) if rows else np.zeros(0, int)
        rows = np.concatenate(rows) if rows else np.zeros(0, int)
        point = (np.concatenate([self.image_points(i) for i in dbs]) if len(dbs) else np.zeros(0, np.int64))
        keep = self.track_length[point] >= min_track_length
        if selected is not None:
            n = len(self.names)
            keep &= np.isin(point * n + db, np.asarray(selected, np.int64).reshape(-1, 2) @ np.array([n, 1]))
        return Observations(point[keep], db[keep], rows[keep])

    @functools.cached_property
    def source_ids(self) -> Tuple[Dict[int, int], Dict[int, int]]:
        """Maps from the source model's image and point ids to the store's indices (built once)."""
        images = {int(s): i for i, s in enumerate(self.image_source_id) if s >= 0}
        points = {int(s): i for i, s in enumerate(self.point_source_id) if s >= 0}
        return images, points

    def _read_block(self, i: int, scale: int) -> Tuple[Dict[str, np.ndarray], int]:
        """Image i's rows at one image scale as stored (features, and their int8 scales, confidences,
        valid), and the bytes read (thread-safe: the callers count and cache it). They are decoded
        per query, for the rows it uses (``_decode``)."""
        s = slice(int(self.row_start[i]), int(self.row_start[i] + self.num_obs[i]))
        arrays = self._block_arrays[scale]
        self._check_present(i, list(arrays.values()))
        out = {}
        for name, array in arrays.items():
            try:
                out[name] = array[s]
            except Exception as e:  # zarr/numcodecs raise many types for a bad chunk  # noqa: BLE001
                raise StoreReadError(f"map store {self.path}: array {array.path} cannot be read for "
                                     f"reference image {self.names[i]}: {type(e).__name__}: {e}") from None
        return out, sum(a.nbytes for a in out.values())

    def _decode(self, block: Dict[str, np.ndarray], rows: np.ndarray, scale: int
                ) -> Tuple[List[np.ndarray], np.ndarray, np.ndarray]:
        """``rows`` of a stored block: per level features (N, C_l) float32 (int8 codes times their
        scales, principal components reconstructed), confidences (N, L) float32, valid (N, L)."""
        if "scales" in block:
            features = dequantize_int8(block["features"][rows], block["scales"][rows], self.stored_dims)
        else:
            edges = np.cumsum([0] + self.stored_dims)
            stored = block["features"][rows]
            features = [stored[:, edges[k]:edges[k + 1]].astype(np.float32) for k in range(len(self.stored_dims))]
        features = [reconstruct(f, self.pca[(scale, level)]) if (scale, level) in self.pca else f
                    for level, f in enumerate(features)]
        return features, block["confidences"][rows].astype(np.float32), block["valid"][rows]

    def clear_cache(self) -> None:
        """Forget every block, row and object read (the next reads go to the store)."""
        if isinstance(self._root.store, location.WholeObjects):
            self._root.store.clear()
        self._blocks.clear()
        self._cached_bytes = 0
        for rows in self._rows.values():
            rows.cache_clear()

    def _concurrently(self, fn, args) -> list:
        """``[fn(a) for a in args]``, run on the reader's threads."""
        if self._read_threads <= 1 or len(args) <= 1:
            return [fn(a) for a in args]
        return list(_read_pool(self._read_threads).map(fn, args))

    def blocks(self, images: List[int], scale: int) -> list:
        """The blocks of ``images`` at ``scale`` as stored (``_read_block``), the ones not cached read
        concurrently; counts cache hits."""
        keys = [(int(i), int(scale)) for i in images]
        todo = list(dict.fromkeys(k for k in keys if k not in self._blocks))
        read = dict(zip(todo, self._concurrently(lambda k: self._read_block(*k), todo)))
        out = {}
        for key in keys:  # the cached ones first: caching the new ones may evict them
            if key in self._blocks and key not in out:
                self._blocks.move_to_end(key)
                self.stats["hits"] += 1
                out[key] = self._blocks[key]
        max_blocks, max_bytes = self._cache_limits
        for key, (block, nbytes) in read.items():
            self._blocks[key] = block
            self._cached_bytes += nbytes
            while len(self._blocks) > 1 and (len(self._blocks) > max_blocks or self._cached_bytes > max_bytes):
                self._cached_bytes -= _nbytes(self._blocks.popitem(last=False)[1])
            self.stats["blocks"] += 1
            self.stats["bytes"] += nbytes
            out[key] = block
        return [out[key] for key in keys]

    def features(self, obs: Observations, scale: int) -> List[Tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per level: features (M, C) float32, confidences (M,), valid (M,) of the observations."""
        M = len(obs.rows)
        out = [(np.zeros((M, dim), np.float32), np.zeros(M, np.float32), np.zeros(M, bool)) for dim in self.dims]
        images = [int(i) for i in np.unique(obs.db)]
        for i, block in zip(images, self.blocks(images, scale)):
            sel = np.flatnonzero(obs.db == i)
            f, w, v = self._decode(block, obs.rows[sel] - self.row_start[i], scale)
            for level, (F, W, V) in enumerate(out):
                F[sel], W[sel], V[sel] = f[level], w[:, level], v[:, level]
        return out


@functools.lru_cache(maxsize=None)
def _read_pool(threads: int) -> ThreadPoolExecutor:
    """The threads that the readers of this process read on: one pool per size, however many
    readers a process opens (a worker opens one per map it localizes against)."""
    return ThreadPoolExecutor(threads, thread_name_prefix="map-store-read")


def _nbytes(block: Dict[str, np.ndarray]) -> int:
    return sum(a.nbytes for a in block.values())


_OPEN: Dict[Tuple, Tuple[Tuple, MapReader]] = {}


def forget_readers() -> None:
    """Drop the readers ``open_reader`` keeps (and their block caches): the next call opens the
    store again, as a new process would."""
    _OPEN.clear()


def open_reader(path, conf: FeatureConfig, digest: Optional[str] = None) -> MapReader:
    """A MapReader shared by the tasks of this process (Dask worker or sync run).

    Opening a store reads its structure (every observation's point, all points), and the
    reader caches the reference blocks it has read: shards of the same map reuse both.
    A store or feature group rewritten since is reopened; which images are usable is
    re-read on every call.
    """
    path = location.normalize(path)
    name = (path, json.dumps(conf.to_dict(), sort_keys=True), digest)
    # changes when the store or the feature group is rewritten
    stamp = location.stamp(path, ("zarr.json", f"features/{feature_key(conf)}/zarr.json"))
    cached = _OPEN.get(name)
    if cached is not None and cached[0] == stamp:
        cached[1].refresh()
        return cached[1]
    reader = MapReader(path, conf, digest)
    _OPEN.clear()  # one map per process at a time: the block cache can be large
    _OPEN[name] = (stamp, reader)
    return reader


def by_name(reader: MapReader, names: List[str]) -> Tuple[List[int], List[str]]:
    """Indices of reference names, and the names not in the map."""
    found = [reader.index[n] for n in names if n in reader.index]
    return found, [n for n in names if n not in reader.index]

