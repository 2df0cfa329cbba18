"""The per-model feature groups of a map store (``features/<key>/``, layout in ``pipeline.store.layout``
and docs/map_store.md): their name, creation and checks, the writing of one image's rows, and the
consolidated copies that readers open fast. A group's ``status`` is per image: pending, done or
failed (with a reason)."""

import functools
from dataclasses import fields
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import zarr

from pipeline.store.compression import project, quantize_int8
from pipeline.descriptors import DESCRIPTORS, UNNAMED_DESCRIPTOR
from pipeline.store.schema import FeatureConfig, ImageFeatures
from pipeline.images import file_sha256
from pipeline.keypoints import DESCRIPTOR_DIM
from pipeline.scene import ImageRecord, Scene
from pipeline.store.layout import (DONE, FAILED, PENDING, StoreError, consolidate, consolidated, image_records,
                                   image_rows, new_array, new_rows_array, open_store, padded_rows, read, store_index,
                                   unconsolidate, write_rows)


@functools.lru_cache(maxsize=16)
def _file_digest(path: str, size: int, mtime_ns: int) -> str:
    return file_sha256(path)[:8]  # cached while the file keeps its size and time


KEYED = ("model", "resize", "image_scales", "pad", "dtype", "descriptor", "pca", "sift")  # named in every key


def feature_key(conf: FeatureConfig) -> str:
    """The store group of a feature config: derived from it, so two configs never share one.
    A model file is named by its stem and the digest of its bytes: two different ``model.pt``
    files never share a group. A setting added to ``FeatureConfig`` later is named only where it
    differs from its default: the groups made before it keep their keys."""
    name = conf.model
    if Path(conf.model).suffix:
        path = Path(conf.model)
        name = path.stem
        if path.is_file():
            st = path.stat()
            name = f"{name}-{_file_digest(str(path.resolve()), st.st_size, st.st_mtime_ns)}"
    scales = "-".join(str(s) for s in conf.image_scales)
    dtype = "" if conf.dtype == "float16" else f"_{conf.dtype}"
    descriptor = "" if conf.descriptor == UNNAMED_DESCRIPTOR else f"_{conf.descriptor}"
    pca = f"_pca{conf.pca}" if conf.pca else ""
    sift = f"_sift{conf.sift}" if conf.sift else ""
    later = "".join(f"_{f.name}{getattr(conf, f.name)}" for f in fields(conf)
                    if f.name not in KEYED and getattr(conf, f.name) != f.default)
    return f"{name}_r{conf.resize}_s{scales}_p{conf.pad}{dtype}{descriptor}{pca}{sift}{later}"


def descriptor_dim(kind: str, channels: int) -> int:
    """Length of the global descriptor ``kind`` of a ``channels``-channel feature map."""
    return DESCRIPTORS.entry(kind)().dim(channels)


PCABases = Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray]]


def init_features(root: zarr.Group, conf: FeatureConfig, digest: str, dims: List[int],
                  pca: Optional[PCABases] = None) -> zarr.Group:
    """Create (or check and reuse) the feature group of ``conf``; another model is refused.

    With ``conf.pca``, creating the group needs ``pca``: per (image scale, level) stored reduced,
    the mean (C,) and basis (C, D) (``fit_pca``); ``needs_pca`` says when."""
    key = feature_key(conf)
    expected = {"config": conf.to_dict(), "model_digest": digest, "dims": list(dims)}
    if f"features/{key}" in root:
        group = root[f"features/{key}"]
        stored = {k: group.attrs.get(k) for k in expected}
        if not conf.made(stored["config"]) or {**stored, "config": expected["config"]} != expected:
            raise StoreError(
                f"The store's features {key!r} were made with {stored}, not {expected}: refusing to mix "
                "them. Use another store or feature config, or rebuild with overwrite.")
        return group
    meta = root.attrs["pixloc_map"]
    I, R, L = meta["num_images"], meta["num_rows"], len(dims)  # noqa: E741
    stored = conf.stored_dims(dims)
    bases: PCABases = {}
    if stored != list(dims):
        if pca is None:
            raise ValueError(f"Feature group {key!r} stores a PCA of the features: it is created with its bases "
                             "(pipeline.mapping.build.write_structure fits them).")
        bases = pca
    group = root.create_group(f"features/{key}")
    group.attrs.update(expected)
    new_array(group, "status", (I,), (1,), "int8", fill_value=PENDING)
    new_array(group, "reason", (I,), (1,), str)
    D = descriptor_dim(conf.descriptor, dims[-1])
    new_array(group, "global", (I, D), (1, D), "float32", fill_value=0)
    for k in range(len(conf.image_scales)):
        for level, (d, kept) in enumerate(zip(dims, stored)):
            if kept < d:
                mean, basis = bases[(k, level)]
                if mean.shape != (d,) or basis.shape != (d, kept):
                    raise ValueError(f"PCA of image scale {k}, level {level}: shapes {mean.shape} and {basis.shape}, "
                                     f"expected {(d,)} and {(d, kept)}.")
                new_array(group, f"s{k}/pca_mean_{level}", (d,), (d,), "float32")[:] = mean
                new_array(group, f"s{k}/pca_basis_{level}", (d, kept), (d, kept), "float32")[:] = basis
        new_rows_array(group, f"s{k}/features", R, sum(stored), conf.dtype, meta, fill_value=0)
        if conf.dtype == "int8":
            new_rows_array(group, f"s{k}/scales", R, L, "float16", meta, fill_value=0)
        new_rows_array(group, f"s{k}/confidences", R, L, "float16" if conf.dtype == "int8" else conf.dtype, meta,
                    fill_value=0)
        new_rows_array(group, f"s{k}/valid", R, L, "bool", meta, fill_value=False)
    if conf.sift:
        new_rows_array(group, "sift", R, DESCRIPTOR_DIM, "uint8", meta, fill_value=0)
    return group


def needs_pca(root: zarr.Group, conf: FeatureConfig) -> bool:
    """Whether ``init_features`` will create the group of ``conf`` stored as a PCA (its bases are
    fitted first, on the map's images)."""
    return bool(conf.pca) and f"features/{feature_key(conf)}" not in root


def pca_bases(group: zarr.Group) -> PCABases:
    """{(image scale, level): (mean, directions)} of a feature group stored as a PCA (else empty)."""
    conf = group.attrs["config"]
    pca = int(conf.get("pca", 0))
    if not pca:
        return {}
    return {(k, level): (group[f"s{k}/pca_mean_{level}"][:], group[f"s{k}/pca_basis_{level}"][:])
            for k in range(len(conf["image_scales"])) for level, d in enumerate(group.attrs["dims"]) if d > pca}


def write_image_features(group: zarr.Group, root: zarr.Group, i: int, feats: ImageFeatures) -> None:
    """Write image i's rows (whole shards), then mark it done: status last, so a crash leaves it pending."""
    bases = pca_bases(group)
    columns = {}  # (array path in the group, its values)
    for k in range(len(group.attrs["config"]["image_scales"])):
        levels = [feats.samples[(k, level)] for level in range(len(group.attrs["dims"]))]
        kept = [project(x[0], bases[(k, level)]) if (k, level) in bases else x[0] for level, x in enumerate(levels)]
        f = np.concatenate(kept, 1)
        if f"s{k}/scales" in group:
            f, columns[f"s{k}/scales"] = quantize_int8(f, [x.shape[1] for x in kept])
        columns[f"s{k}/features"] = f
        columns[f"s{k}/confidences"] = np.stack([x[1] for x in levels], 1)
        columns[f"s{k}/valid"] = np.stack([x[2] for x in levels], 1)
    rows = image_rows(root, i)
    if "sift" in group:
        if feats.sift is None or feats.sift.shape != (rows.stop - rows.start, DESCRIPTOR_DIM):
            raise StoreError(f"Image {i}: the feature group stores SIFT descriptors, {rows.stop - rows.start} rows, "
                             "and none or other rows were extracted.")
        columns["sift"] = feats.sift
    block = slice(rows.start, rows.start + int(padded_rows(np.array(rows.stop - rows.start),
                                                           root.attrs["pixloc_map"]["shard_rows"])))
    for name, values in columns.items():
        write_rows(group[name], block, values)
    group["global"][i] = feats.global_descriptor.astype(np.float32)
    group["reason"][i] = ""
    group["status"][i] = DONE


def mark_failed(group: zarr.Group, i: int, reason: str) -> None:
    group["reason"][i] = reason
    group["status"][i] = FAILED


class FeatureWriter:
    """The one writer of a feature group: the group of ``conf`` in the store at ``path``, opened for
    writing (created when it is not there, with the PCA bases that ``fit_pca()`` gives where
    ``needs_pca``). Another model's group of the same key is refused (``StoreError``). What the map
    build (``pipeline.mapping.build``) asks of the store, without its keys: which images are done,
    failed (and why) or pending, an image's observed points, its features (rows first, status last)
    or its failure; ``finish_group`` consolidates the group when the build is over. Opened for the
    build of a ``scene``, it holds the store's index of each of its images (``index``: the store keeps
    its own order) and every image's ``status`` (PENDING, DONE, FAILED) and ``reasons``."""

    def __init__(self, path, conf: FeatureConfig, digest: str, dims: List[int],
                 fit_pca: Optional[Callable[[], PCABases]] = None, scene: Optional[Scene] = None):
        self.root = open_store(path, mode="r+")
        pca = fit_pca() if fit_pca is not None and needs_pca(self.root, conf) else None
        self.group = init_features(self.root, conf, digest, dims, pca=pca)
        self.meta = self.root.attrs["pixloc_map"]
        if scene is not None:  # opened for a build of ``scene``: ``index``, ``status``, ``reasons``
            self.status = read(self.group, "status", self.meta)
            self.reasons = read(self.group, "reason", self.meta).astype(object)
            if not consolidated(self.group, self.meta) or (self.status != DONE).any():
                unconsolidate(self.group)  # images will be written: readers use the per-image arrays meanwhile
            self.index = store_index(self.root, scene)  # scene order -> store order

    def contents(self) -> Tuple[List[ImageRecord], np.ndarray]:
        """The map's images (records) and points (N, 3)."""
        return image_records(self.root), self.root["points/xyz"][:]

    def state(self, i: int) -> Tuple[int, str, np.ndarray]:
        """Image i's status, reason, and the points it observes (in its rows' order)."""
        start, n = int(self.root["images/row_start"][i]), int(self.root["images/num_obs"][i])
        return int(self.group["status"][i]), str(self.group["reason"][i]), \
            self.root["observations/point"][start:start + n]

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
