"""The zarr map store: images, points, observations and per-model reference features.

Layout (version 1, documented in docs/map_store.md):

    map.zarr/                     attrs: pixloc_map {version, chunk_rows, num_images, ...}
      images/name, camera, tags   (I,) str (camera and tags as JSON)
      images/cam_from_world       (I, 12) float64, [R row-major | t]
      images/row_start, num_obs   (I,) int64: image i owns rows [row_start, row_start + padded)
      images/source_id            (I,) int64: id in the source model (COLMAP image_id), -1 if none
      points/xyz                  (P, 3) float64
      points/track_length         (P,) int32
      points/source_id            (P,) int64: id in the source model (COLMAP point3D_id), -1 if none
      observations/point          (R,) int64, -1 on padding rows
      observations/xy             (R, 2) float32, COLMAP pixel coordinates (NaN if unknown)
      features/<key>/             attrs: config, model digest, level dims
        status (I,) int8 (0 pending, 1 done, 2 failed), reason (I,) str   [chunk 1]
        global (I, D) float32                                             [chunk (1, D)]
        s{k}/l{l}/features (R, C_l) float16, confidences (R,) float16, valid (R,) bool

Rows are grouped by image and each image's block is padded to a multiple of
``chunk_rows``, so every chunk belongs to one image: workers writing
different images never write the same chunk, and a build resumes image by
image from ``status``.
"""

import json
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import zarr

from .features import FeatureConfig, ImageFeatures
from .scene import CameraRecord, ImageRecord, Scene

VERSION = 1
PENDING, DONE, FAILED = 0, 1, 2


class StoreError(ValueError):
    """A store that does not exist, has another layout, or another model or config."""


def _padded(n: np.ndarray, chunk: int) -> np.ndarray:
    return np.maximum(1, -(-n // chunk)) * chunk


def create_store(path, scene: Scene, chunk_rows: int = 256, overwrite: bool = False,
                 source: Optional[Dict] = None) -> zarr.Group:
    """Write the scene's structure; an existing store of the same scene is reused as is."""
    path = Path(path)
    names = [im.name for im in scene.images]
    if path.exists() and not overwrite:
        root = open_store(path, mode="r+")
        if list(root["images/name"][:]) != names or int(root.attrs["pixloc_map"]["num_observations"]) != len(
                scene.obs_point):
            raise StoreError(f"{path} holds another map (other images or observations); "
                             "choose another path or pass overwrite.")
        return root
    order = np.lexsort((scene.obs_point, scene.obs_image))
    obs_image, obs_point, obs_xy = scene.obs_image[order], scene.obs_point[order], scene.obs_xy[order]
    num_obs = np.bincount(obs_image, minlength=len(scene.images))
    padded = _padded(num_obs, chunk_rows)
    row_start = np.concatenate([[0], np.cumsum(padded)[:-1]])
    rows = int(padded.sum())
    # row of each observation: its image's block start + its rank inside the image
    rank = np.arange(len(obs_image)) - np.concatenate([[0], np.cumsum(num_obs)[:-1]])[obs_image]
    row = row_start[obs_image] + rank

    root = zarr.open_group(str(path), mode="w")
    root.attrs["pixloc_map"] = {
        "version": VERSION, "chunk_rows": chunk_rows, "num_images": len(names),
        "num_points": len(scene.points), "num_observations": int(len(obs_point)), "num_rows": rows,
        "source": source or {}}
    I = len(names)  # noqa: E741
    root.create_array("images/name", shape=(I,), chunks=(I,), dtype=str)[:] = np.array(names)
    root.create_array("images/camera", shape=(I,), chunks=(I,), dtype=str)[:] = np.array(
        [im.camera.to_json() for im in scene.images])
    root.create_array("images/tags", shape=(I,), chunks=(I,), dtype=str)[:] = np.array(
        [json.dumps(im.tags, sort_keys=True) for im in scene.images])
    root.create_array("images/path", shape=(I,), chunks=(I,), dtype=str)[:] = np.array(
        [str(im.path) for im in scene.images])
    root.create_array("images/cam_from_world", shape=(I, 12), chunks=(I, 12), dtype="float64")[:] = np.stack(
        [np.concatenate([np.asarray(im.cam_from_world)[:, :3].reshape(-1), np.asarray(im.cam_from_world)[:, 3]])
         for im in scene.images])
    root.create_array("images/row_start", shape=(I,), chunks=(I,), dtype="int64")[:] = row_start
    root.create_array("images/num_obs", shape=(I,), chunks=(I,), dtype="int64")[:] = num_obs
    root.create_array("images/source_id", shape=(I,), chunks=(I,), dtype="int64")[:] = np.array(
        [im.source_id for im in scene.images], dtype=np.int64)
    P = len(scene.points)
    root.create_array("points/xyz", shape=(P, 3), chunks=(max(P, 1), 3), dtype="float64")[:] = scene.points
    root.create_array("points/track_length", shape=(P,), chunks=(max(P, 1),), dtype="int32")[:] = scene.track_length
    root.create_array("points/source_id", shape=(P,), chunks=(max(P, 1),), dtype="int64")[:] = scene.point_ids
    point = np.full(rows, -1, dtype=np.int64)
    point[row] = obs_point
    xy = np.full((rows, 2), np.nan, dtype=np.float32)
    xy[row] = obs_xy
    chunk = max(chunk_rows * 64, 1)
    root.create_array("observations/point", shape=(rows,), chunks=(chunk,), dtype="int64", fill_value=-1)[:] = point
    root.create_array("observations/xy", shape=(rows, 2), chunks=(chunk, 2), dtype="float32")[:] = xy
    return root


def open_store(path, mode: str = "r") -> zarr.Group:
    path = Path(path)
    if not path.exists():
        raise StoreError(f"Map store {path} does not exist.")
    root = zarr.open_group(str(path), mode=mode)
    meta = root.attrs.get("pixloc_map")
    if not meta:
        raise StoreError(f"{path} is not a PixLoc map store.")
    if meta.get("version") != VERSION:
        raise StoreError(f"{path} has map-store version {meta.get('version')}; this code reads version {VERSION}.")
    return root


def feature_key(conf: FeatureConfig) -> str:
    """The store group of a feature config: derived from it, so two configs never share one."""
    name = Path(conf.model).stem if Path(conf.model).suffix else conf.model
    scales = "-".join(str(s) for s in conf.image_scales)
    dtype = "" if conf.dtype == "float16" else f"_{conf.dtype}"
    descriptor = "" if conf.descriptor == "gem" else f"_{conf.descriptor}"
    return f"{name}_r{conf.resize}_s{scales}_p{conf.pad}{dtype}{descriptor}"


def descriptor_dim(kind: str, channels: int) -> int:
    """Length of the global descriptor ``kind`` of a ``channels``-channel feature map."""
    return channels * 6 if kind == "grid" else channels


def init_features(root: zarr.Group, conf: FeatureConfig, digest: str, dims: List[int]) -> zarr.Group:
    """Create (or check and reuse) the feature group of ``conf``; another model is refused."""
    key = feature_key(conf)
    expected = {"config": conf.to_dict(), "model_digest": digest, "dims": list(dims)}
    if f"features/{key}" in root:
        group = root[f"features/{key}"]
        stored = {k: group.attrs.get(k) for k in expected}
        if stored != expected:
            raise StoreError(
                f"The store's features {key!r} were made with {stored}, not {expected}: refusing to mix "
                "them. Use another store or feature config, or rebuild with overwrite.")
        return group
    meta = root.attrs["pixloc_map"]
    I, R, chunk = meta["num_images"], meta["num_rows"], meta["chunk_rows"]  # noqa: E741
    group = root.create_group(f"features/{key}")
    group.attrs.update(expected)
    group.create_array("status", shape=(I,), chunks=(1,), dtype="int8", fill_value=PENDING)
    group.create_array("reason", shape=(I,), chunks=(1,), dtype=str)
    D = descriptor_dim(conf.descriptor, dims[-1])
    group.create_array("global", shape=(I, D), chunks=(1, D), dtype="float32", fill_value=0)
    for k in range(len(conf.image_scales)):
        for level, dim in enumerate(dims):
            g = f"s{k}/l{level}"
            group.create_array(f"{g}/features", shape=(R, dim), chunks=(chunk, dim), dtype=conf.dtype, fill_value=0)
            group.create_array(f"{g}/confidences", shape=(R,), chunks=(chunk,), dtype=conf.dtype, fill_value=0)
            group.create_array(f"{g}/valid", shape=(R,), chunks=(chunk,), dtype="bool", fill_value=False)
    return group


def image_records(root: zarr.Group) -> List[ImageRecord]:
    """The stored images as records (paths as recorded at build time)."""
    T = root["images/cam_from_world"][:]
    return [ImageRecord(str(n), Path(str(p)), CameraRecord.from_json(str(c)),
                        np.concatenate([t[:9].reshape(3, 3), t[9:, None]], 1), json.loads(str(g)))
            for n, p, c, g, t in zip(root["images/name"][:], root["images/path"][:], root["images/camera"][:],
                                     root["images/tags"][:], T)]


def image_rows(root: zarr.Group, i: int) -> slice:
    """The rows of image i (its observations first, then padding)."""
    start = int(root["images/row_start"][i])
    return slice(start, start + int(root["images/num_obs"][i]))


def write_image_features(group: zarr.Group, root: zarr.Group, i: int, feats: ImageFeatures) -> None:
    """Write image i's rows (whole chunks), then mark it done: status last, so a crash leaves it pending."""
    rows = image_rows(root, i)
    chunk = root.attrs["pixloc_map"]["chunk_rows"]
    block = slice(rows.start, rows.start + int(_padded(np.array(rows.stop - rows.start), chunk)))
    n_pad = block.stop - block.start
    for (k, level), (f, c, v) in feats.samples.items():
        g = group[f"s{k}/l{level}"]
        dtype = g["features"].dtype
        fp = np.zeros((n_pad, f.shape[1]), dtype)
        fp[: len(f)] = f
        cp = np.zeros(n_pad, dtype)
        cp[: len(c)] = c
        vp = np.zeros(n_pad, bool)
        vp[: len(v)] = v
        g["features"][block] = fp
        g["confidences"][block] = cp
        g["valid"][block] = vp
    group["global"][i] = feats.global_descriptor.astype(np.float32)
    group["reason"][i] = ""
    group["status"][i] = DONE


def mark_failed(group: zarr.Group, i: int, reason: str) -> None:
    group["reason"][i] = reason
    group["status"][i] = FAILED
