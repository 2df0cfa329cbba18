"""The zarr map store: images, points, observations and per-model reference features.

Layout (version 3, documented in docs/map_store.md):

    map.zarr/                     attrs: pixloc_map {version, chunk_rows, shard_rows, num_images, ...}
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
        s{k}/features (R, C) every level's channels side by side (C = sum of dims):
                      float16, float32, or int8 with s{k}/scales (R, L) float16
        s{k}/confidences (R, L) float16, s{k}/valid (R, L) bool
        s{k}/pca_mean_{l} (C_l,), s{k}/pca_basis_{l} (C_l, D) float32   [config pca = D > 0: the
                      levels with C_l > D are stored as their D principal components]

Rows are grouped by image and each image's block is padded to a multiple of
``shard_rows``: every shard (one file per array, inner chunks of ``chunk_rows``
rows) belongs to one image, so workers writing different images never write the
same file, and a build resumes image by image from ``status``. Padding costs no
disk: chunks of fill values are not written.

Every chunk is checksummed (zstd, then a CRC-32C codec, and a CRC-32C of each shard
index): a flipped byte or a truncated file is an error naming its array, never silent
garbage. ``open_store`` checks the layout (every array present, shapes that agree
with the attributes) before anything is read, and ``check_feature_group`` a feature group's
(``features/<key>/``) before a reader uses it; feature groups are named, created and written
by ``pipeline.store.feature_groups``.
"""

import contextlib
import json
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import zarr
from zarr.codecs import Crc32cCodec, ZstdCodec

from pipeline.keypoints import DESCRIPTOR_DIM
from pipeline.store import location
from pipeline.scene import CameraRecord, ImageRecord, Scene

VERSION = 3
PENDING, DONE, FAILED = 0, 1, 2
MAX_ROWS_PER_OBSERVATION = 64  # rows are observations plus padding to whole chunks: far fewer


def _codecs():
    """Compression then a CRC-32C checksum of each chunk (zarr v3 codecs)."""
    return [ZstdCodec(level=3), Crc32cCodec()]


def new_array(group: zarr.Group, name: str, shape, chunks, dtype, **kwargs) -> zarr.Array:
    return group.create_array(name, shape=shape, chunks=chunks, dtype=dtype, compressors=_codecs(), **kwargs)


def new_rows_array(group: zarr.Group, name: str, rows: int, width: Optional[int], dtype, meta: Dict,
                **kwargs) -> zarr.Array:
    """A per-row array: inner chunks of ``chunk_rows`` rows in shards of ``shard_rows`` (one per image block)."""
    tail = () if width is None else (width,)
    return new_array(group, name, (rows,) + tail, (meta["chunk_rows"],) + tail, dtype,
                  shards=(meta["shard_rows"],) + tail, **kwargs)


class StoreError(ValueError):
    """A store that does not exist, has another layout, or another model or config."""


class AnotherMap(StoreError):
    """A build whose scene differs from the map the store already holds."""


class StoreReadError(StoreError):
    """A chunk of the store that cannot be read (corrupt, truncated, checksum mismatch):
    fails the query that needed it, not the run."""


def padded_rows(n: np.ndarray, chunk: int) -> np.ndarray:
    return np.maximum(1, -(-n // chunk)) * chunk


def count(meta: Dict, name: str) -> int:
    """The committed length of an array's first axis (arrays may be longer while images are being
    added: the map attributes are the commit point)."""
    if name.startswith("images/") or name.split("/")[-1] in ("status", "reason", "global", "status_all",
                                                             "global_all"):
        return meta["num_images"]
    if name.startswith("points/"):
        return meta["num_points"]
    return meta["num_rows"]


def read(group: zarr.Group, name: str, meta: Optional[Dict] = None) -> np.ndarray:
    """Array ``name`` of ``group`` up to its committed length (``count``); ``meta``: the map
    attributes (default: those of ``group``, the root)."""
    meta = meta if meta is not None else group.attrs["pixloc_map"]
    array, n = group[name], count(meta, name)
    if n and dense(array.path):  # every chunk holds data: an absent one is never read as fill values
        missing = missing_objects(array, slice(0, n))
        if missing:
            raise StoreReadError(f"array {array.path}: {len(missing)} of its files are missing or not files "
                                 f"({missing[0]}): a damaged store; run pixloc check-store")
    return array[:n]


def dense(path: str) -> bool:
    """Whether every chunk of the array at ``path`` holds data: the map's structure, written whole
    (``images/``, ``points/``), and a feature group's one-chunk copies and PCA bases. Per-row arrays
    (padding) and per-image arrays (pending images) have chunks that are never written."""
    last = path.rsplit("/", 1)[-1]
    return path.startswith(("images/", "points/")) or last in ("status_all", "global_all") or last.startswith("pca_")


def missing_objects(arrays, rows: slice) -> List[str]:
    """The storage objects (shard files, or chunks of unsharded arrays) that hold rows ``rows`` of
    ``arrays`` (one array or several) and are absent, empty, or not plain files: zarr reads those
    as fill values (zeros, -1), so every reader of an image's rows asks here first. Keys relative
    to the store. The objects are asked about together (against object storage, one round trip).
    An empty ``rows`` has none: the map's structure is written whole, so an image without observations
    (an unmatched photo of a triangulated map) has no shard of its own there, and nothing to read."""
    import asyncio

    from zarr.core.sync import sync

    arrays = [arrays] if isinstance(arrays, zarr.Array) else list(arrays)
    objects = []
    for array in arrays if rows.stop > rows.start else ():  # no rows (an image without observations): none missing
        unit = (array.shards or array.chunks)[0]
        for k in range(rows.start // unit, -(-rows.stop // unit)):
            key = array.metadata.encode_chunk_key((k,) + (0,) * (array.ndim - 1))
            objects.append((f"{array.path}/{key}", array.store_path / key))

    async def absent(where) -> bool:
        # an empty object is as missing as an absent one: a chunk or a shard index is never 0 bytes
        return not await where.exists() or not await where.store.getsize(where.path)

    async def ask():
        return await asyncio.gather(*(absent(where) for _, where in objects))

    return [name for (name, _), gone in zip(objects, sync(ask()) if objects else []) if gone]


def image_row_arrays(root: zarr.Group, group: Optional[zarr.Group] = None) -> List[zarr.Array]:
    """The per-row arrays an image's data lives in: its observations, and the rows of every image
    scale of the feature ``group`` (all groups when None)."""
    arrays = [root["observations/point"], root["observations/xy"]]
    groups = [group] if group is not None else ([g for _, g in root["features"].groups()] if "features" in root
                                                else [])
    for g in groups:
        arrays += feature_row_arrays(g)
    return arrays


def feature_row_arrays(group: zarr.Group) -> List[zarr.Array]:
    """A feature group's arrays of one row per observation: every image scale's (not its PCA
    bases) and the SIFT descriptors where it stores them."""
    arrays = [a for _, scale in sorted(group.groups()) for name, a in sorted(scale.arrays())
              if not name.startswith("pca_")]
    return arrays + ([group["sift"]] if "sift" in group else [])


def unconsolidate(group: zarr.Group) -> None:
    """Readers of feature ``group`` go back to its per-image arrays (a build or an add is about to
    change them; ``consolidate`` makes the copies again)."""
    if group.attrs.get("consolidated"):
        group.attrs["consolidated"] = False


def write_rows(array: zarr.Array, block: slice, values: np.ndarray) -> None:
    """An image's rows, padded to its whole block, written even where they are all fill values (a
    valid mask all False, SIFT descriptors all zero): zarr would otherwise leave the shard out, and
    a done image's absent shard is a missing file to every reader (``missing_objects``)."""
    out = np.zeros((block.stop - block.start,) + values.shape[1:], array.dtype)
    out[: len(values)] = values
    array.with_config({"write_empty_chunks": True})[block] = out


def consolidate(root: zarr.Group, group: zarr.Group) -> None:
    """Copy the per-image ``status`` and ``global`` arrays (one chunk per image, so that workers
    write their own) into one chunk each, for readers: reading 6,697 one-image chunks takes
    seconds, on every open. Called when a build has finished; ``unconsolidate`` before the next
    one writes. The copy is valid while ``attrs["consolidated"]`` names the image count."""
    meta = root.attrs["pixloc_map"]
    I = meta["num_images"]  # noqa: E741
    status, descriptors = read(group, "status", meta), read(group, "global", meta)
    for name, values in (("status_all", status), ("global_all", descriptors)):
        if name in group:
            del group[name]
        array = new_array(group, name, values.shape, values.shape if len(values) else (1,) + values.shape[1:],
                          values.dtype)
        array.with_config({"write_empty_chunks": True})[...] = values  # dense: read back only if on disk
    group.attrs["consolidated"] = {"num_images": I}


def consolidated(group: zarr.Group, meta: Dict) -> bool:
    """Whether feature ``group``'s one-chunk copies (status_all, global_all) are current."""
    return group.attrs.get("consolidated") == {"num_images": meta["num_images"]} and "status_all" in group


def open_store(path, mode: str = "r") -> zarr.Group:
    """Open a map store (a folder or a URL, ``pipeline.store.location``) after checking its layout
    (``check_layout``); a bad one is refused with a StoreError that says what is wrong."""
    try:
        with location.waiting_note(path, "the map's metadata") if location.is_url(path) else contextlib.nullcontext():
            return checked_root(location.zarr_store(path, read_only=mode == "r", must_exist=True), path, mode)
    except location.MissingStore:
        raise StoreError(f"Map store {path} does not exist.") from None
    except (OSError, ValueError) as e:  # a URL that cannot be reached, bad storage options
        if isinstance(e, StoreError):
            raise
        if isinstance(e, location.StoreLocationError):  # names the store and what to do already
            raise StoreError(str(e)) from None
        raise StoreError(f"Map store {path} cannot be reached: {type(e).__name__}: {e}") from None


def checked_root(store, path, mode: str) -> zarr.Group:
    try:
        root = zarr.open_group(store=store, mode=mode)
        meta = root.attrs.get("pixloc_map")
    except Exception as e:  # unreadable or invalid zarr.json  # noqa: BLE001
        raise StoreError(f"{path} is not a readable zarr group: {type(e).__name__}: {e}") from None
    if not meta:
        raise StoreError(f"{path} is not a PixLoc map store.")
    if not isinstance(meta, dict):
        raise StoreError(f"{path}: its map attributes (pixloc_map in zarr.json) are a {type(meta).__name__}, not "
                         "an object (a damaged store).")
    if type(meta.get("version")) is not int:
        raise StoreError(f"{path}: its map-store version is {json.dumps(meta.get('version'))}, not a whole number "
                         "(a damaged zarr.json).")
    if meta.get("version") != VERSION:
        raise StoreError(f"{path} has map-store version {meta.get('version')}; this code reads version {VERSION} "
                         "(version 2 added chunk checksums, version 3 one file per image and array, and int8 "
                         "features): rebuild it with pixloc build-map --overwrite.")
    check_layout(root, path)
    return root


def _expected_arrays(meta: Dict) -> Dict[str, tuple]:
    I, P, R = meta["num_images"], meta["num_points"], meta["num_rows"]  # noqa: E741
    return {"images/name": (I,), "images/camera": (I,), "images/tags": (I,), "images/path": (I,),
            "images/cam_from_world": (I, 12), "images/row_start": (I,), "images/num_obs": (I,),
            "images/source_id": (I,), "points/xyz": (P, 3), "points/track_length": (P,),
            "points/source_id": (P,), "observations/point": (R,), "observations/xy": (R, 2)}


def get_array(group: zarr.Group, name: str, path) -> zarr.Array:
    try:
        return group[name]
    except location.StoreObjectError as e:  # names the file and what is wrong with it
        raise StoreError(str(e)) from None
    except Exception:  # missing, or metadata that does not parse  # noqa: BLE001
        prefix = f"{group.path}/" if group.path else ""
        raise StoreError(f"{path}: array {prefix}{name} is missing or its metadata is unreadable "
                         "(a damaged or partly copied store).") from None


def check_layout(root: zarr.Group, path) -> None:
    """Refuse a store whose attributes contradict each other or its arrays (a missing array, a
    shape that disagrees, absurd sizes), before any large read or allocation."""
    meta = root.attrs["pixloc_map"]
    keys = ("chunk_rows", "shard_rows", "num_images", "num_points", "num_observations", "num_rows")
    bad = {k: meta.get(k) for k in keys if type(meta.get(k)) is not int or meta[k] < 0}  # bool is no count
    if bad:
        raise StoreError(f"{path}: map attributes {json.dumps(bad)} must be counts (whole numbers >= 0): a damaged "
                         "zarr.json.")
    if "scene_observations" in meta and (type(meta["scene_observations"]) is not int
                                         or meta["scene_observations"] < meta["num_observations"]):
        raise StoreError(f"{path}: map attribute scene_observations {json.dumps(meta['scene_observations'])} must "
                         f"be a count of at least num_observations ({meta['num_observations']}).")
    if not isinstance(meta.get("source", {}), dict):
        raise StoreError(f"{path}: map attribute source must be an object, not {json.dumps(meta['source'])[:40]}.")
    I, R, chunk, shard = meta["num_images"], meta["num_rows"], meta["chunk_rows"], meta["shard_rows"]  # noqa: E741
    if (chunk < 1 or shard < chunk or shard % chunk
            or not meta["num_observations"] <= R <= meta["num_observations"] + max(I, 1) * shard):
        raise StoreError(f"{path}: {R} rows for {meta['num_observations']} observations of {I} images in shards "
                         f"of {shard} rows (chunks of {chunk}): the attributes contradict each other "
                         "(a damaged store?).")
    longer = []
    for name, shape in _expected_arrays(meta).items():
        array = get_array(root, name, path)
        if tuple(array.shape[1:]) != shape[1:] or array.shape[0] < shape[0]:  # longer: an add was interrupted
            raise StoreError(f"{path}: array {name} has shape {tuple(array.shape)}, the map attributes say {shape}.")
        if array.shape[0] > shape[0]:
            longer.append((name, array.shape[0], shape[0]))
    # an interrupted add (``structure.extend_store``) lengthens the image arrays first: points or rows beyond
    # the committed counts with no image beyond them are a count that was changed, not an add
    if longer and not any(name.startswith("images/") for name, _, _ in longer):
        name, stored, said = next(x for x in longer if not x[0].startswith("images/"))
        raise StoreError(f"{path}: array {name} holds {stored} rows but the map attributes count {said} (and no "
                         "image is being added): the attributes contradict the arrays (a damaged zarr.json).")
        if not name.startswith("observations/"):  # the map's structure: every chunk holds data
            missing = missing_objects(array, slice(0, shape[0])) if shape[0] else []
            if missing:
                raise StoreError(f"{path}: {len(missing)} files of array {name} are missing ({missing[0]}): the "
                                 "map's structure is incomplete (a damaged or partly copied store); rebuild it "
                                 "with build-map --overwrite.")


def check_feature_group(group: zarr.Group, meta: Dict, path) -> None:
    """Refuse a feature group whose arrays are missing or disagree with its config and dims."""
    try:
        raw, config = group.attrs["dims"], group.attrs["config"]
        if not isinstance(raw, list) or not raw or not all(type(d) is int and d > 0 for d in raw):
            raise ValueError(f"dims {json.dumps(raw)[:60]} are not channel counts")
        if not isinstance(config, dict) or type(config.get("pca", 0)) is not int or config.get("pca", 0) < 0:
            raise ValueError(f"config {json.dumps(config)[:80]} is not a feature config")
        dims, scales = list(raw), len(config["image_scales"])
    except (KeyError, TypeError, ValueError) as e:
        raise StoreError(f"{path}: feature group {group.path} has no readable config or dims ({e}).") from None
    I, R, L = meta["num_images"], meta["num_rows"], len(dims)  # noqa: E741
    stored = stored_dims(group)
    expected = {"status": (I,), "reason": (I,)}
    for k in range(scales):
        expected.update({f"s{k}/features": (R, sum(stored)), f"s{k}/confidences": (R, L), f"s{k}/valid": (R, L)})
        if group.attrs["config"].get("dtype") == "int8":
            expected[f"s{k}/scales"] = (R, L)
        for level, (d, kept) in enumerate(zip(dims, stored)):
            if kept < d:
                expected[f"s{k}/pca_mean_{level}"] = (d,)
                expected[f"s{k}/pca_basis_{level}"] = (d, kept)
    if group.attrs["config"].get("sift"):
        expected["sift"] = (R, DESCRIPTOR_DIM)
    for name, shape in expected.items():
        array = get_array(group, name, path)
        if tuple(array.shape[1:]) != shape[1:] or array.shape[0] < shape[0] or (
                "pca_" in name and tuple(array.shape) != shape):
            raise StoreError(f"{path}: array {group.path}/{name} has shape {tuple(array.shape)}, expected {shape}.")
    bases = [get_array(group, name, path) for name in expected if "pca_" in name]
    missing = missing_objects(bases, slice(0, 1)) if bases else []
    if missing:  # every feature of the group needs them: absent, they would be read as zeros
        raise StoreError(f"{path}: {len(missing)} files of the feature group's PCA bases are missing ({missing[0]}): "
                         "its features cannot be reconstructed; rebuild it with build-map --overwrite.")
    if get_array(group, "global", path).shape[0] < I:
        raise StoreError(f"{path}: array {group.path}/global has {group['global'].shape[0]} rows for {I} images.")


def stored_dims(group: zarr.Group) -> List[int]:
    """The channels a feature group stores per level (fewer than the network's with a PCA)."""
    pca = int(group.attrs["config"].get("pca", 0))
    return [min(int(d), pca) if pca else int(d) for d in group.attrs["dims"]]


def store_index(root: zarr.Group, scene: Scene) -> List[int]:
    """The store's index of each image of ``scene`` (by name: the store keeps its own order)."""
    index = {str(n): i for i, n in enumerate(read(root, "images/name"))}
    return [index[im.name] for im in scene.images]


def image_records(root: zarr.Group) -> List[ImageRecord]:
    """The stored images as records (paths as recorded at build time)."""
    meta = root.attrs["pixloc_map"]
    T = read(root, "images/cam_from_world", meta)
    return [ImageRecord(str(n), Path(str(p)), CameraRecord.from_json(str(c)),
                        np.concatenate([t[:9].reshape(3, 3), t[9:, None]], 1), json.loads(str(g)))
            for n, p, c, g, t in zip(read(root, "images/name", meta), read(root, "images/path", meta),
                                     read(root, "images/camera", meta), read(root, "images/tags", meta), T)]


def tag_families(root: zarr.Group) -> Dict[str, int]:
    """{tag family: how many map images carry it} (``images/tags``)."""
    counts: Dict[str, int] = {}
    for text in read(root, "images/tags"):
        for family in json.loads(str(text)):
            counts[family] = counts.get(family, 0) + 1
    return counts


def image_rows(root: zarr.Group, i: int) -> slice:
    """The rows of image i (its observations first, then padding)."""
    start = int(root["images/row_start"][i])
    return slice(start, start + int(root["images/num_obs"][i]))
