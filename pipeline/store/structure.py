"""Writing a map's structure: a new store from a scene (``create_store``), or the images of a new
mapping session added to a stored map (``extend_store``). The layout they write, and its checks at
open, are ``pipeline.store.layout``'s."""

import json
from typing import Dict, List, Optional

import numpy as np
import zarr

from pipeline.scene import ImageRecord, Scene
from pipeline.store import location
from pipeline.store.layout import (PENDING, VERSION, AnotherMap, StoreError, checked_root, feature_row_arrays,
                                   new_array, new_rows_array, padded_rows, read, unconsolidate)


STORE_ENTRIES = {"zarr.json", "images", "points", "observations", "features"}


def refuse_foreign(path, found: "location.Contents") -> None:
    """--overwrite erases only what is recognisably a map store (or an empty folder): a folder of
    anything else is refused, named, with what it holds (``found``)."""
    if found.is_file:
        raise StoreError(f"{path} is a file, not a map store: --overwrite only replaces a map store.")
    ours = b"pixloc_map" in (found.header or b"")
    if found.entries and not ours and not found.entries <= STORE_ENTRIES:
        raise StoreError(f"{path} is not a PixLoc map store (it holds {', '.join(sorted(found.entries)[:4])}"
                         f"{' ...' if len(found.entries) > 4 else ''}): --overwrite only replaces a map store; "
                         "choose another --store.")
    foreign = location.foreign_files(path)
    if foreign:  # erased with the store otherwise: a localization output, a user's notes
        raise StoreError(f"{path} holds {len(foreign)}{'+' if len(foreign) >= 20 else ''} entries that no build "
                         f"wrote ({', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}): --overwrite would "
                         "erase them with the store; move or remove them first.")


def default_shard_rows(num_obs: np.ndarray, chunk_rows: int, max_chunks: int = 64) -> int:
    """Rows per shard: the 90th percentile of the images' observation counts in whole chunks
    (at most ``max_chunks``), so that most images fill one shard and few span several."""
    q = float(np.quantile(num_obs, 0.9)) if len(num_obs) else 0.0
    return chunk_rows * int(np.clip(np.ceil(q / chunk_rows), 1, max_chunks))


def _flat_pose(T) -> np.ndarray:
    """cam_from_world (3, 4) as stored: [R row-major (9) | t (3)]."""
    T = np.asarray(T, np.float64)
    return np.concatenate([T[:, :3].reshape(-1), T[:, 3]])


def _image_columns(images: List[ImageRecord], row_start: np.ndarray, num_obs: np.ndarray) -> Dict[str, np.ndarray]:
    """The images/* arrays of ``images`` (whose rows start at ``row_start``)."""
    return {"images/name": np.array([im.name for im in images]),
            "images/camera": np.array([im.camera.to_json() for im in images]),
            "images/tags": np.array([json.dumps(im.tags, sort_keys=True) for im in images]),
            "images/path": np.array([str(im.path) for im in images]),
            "images/cam_from_world": np.asarray([_flat_pose(im.cam_from_world) for im in images], np.float64),
            "images/row_start": np.asarray(row_start, np.int64), "images/num_obs": np.asarray(num_obs, np.int64),
            "images/source_id": np.array([im.source_id for im in images], np.int64)}


def create_store(path, scene: Scene, chunk_rows: int = 256, overwrite: bool = False,
                 source: Optional[Dict] = None, shard_rows: Optional[int] = None) -> zarr.Group:
    """Write the scene's structure; an existing store of the same scene is reused as is.

    ``shard_rows`` (a multiple of ``chunk_rows``; default ``default_shard_rows``) is the unit
    each image's block of rows is padded to."""
    names = [im.name for im in scene.images]
    found, store = location.contents(path), location.zarr_store(path)
    if found is not None and not overwrite:
        root = checked_root(store, path, "r+")
        stored = [str(n) for n in read(root, "images/name")]
        meta = root.attrs["pixloc_map"]
        # the scene that built or last extended the store (an added session keeps only the new
        # images' observations, so the store may hold fewer than that scene)
        # compared as sets: an added session's images may sort before the stored ones, and the
        # store keeps its own order (build stages map images by name, ``store_index``)
        if set(stored) == set(names) and len(stored) == len(names) and int(
                meta.get("scene_observations", meta["num_observations"])) == len(scene.obs_point):
            return root
        if len(stored) < len(names) and set(stored) <= set(names):
            extend_store(root, scene)
            return root
        raise AnotherMap(f"{path} holds another map (other images or observations); "
                         "choose another path, rebuild it with --overwrite, or add images with a scene that "
                         "holds every image of the map.")
    if found is not None:
        refuse_foreign(path, found)
    order = np.lexsort((scene.obs_point, scene.obs_image))
    obs_image, obs_point, obs_xy = scene.obs_image[order], scene.obs_point[order], scene.obs_xy[order]
    num_obs = np.bincount(obs_image, minlength=len(scene.images))
    shard_rows = shard_rows or default_shard_rows(num_obs, chunk_rows)
    if shard_rows % chunk_rows:
        raise ValueError(f"shard_rows ({shard_rows}) must be a multiple of chunk_rows ({chunk_rows}).")
    padded = padded_rows(num_obs, shard_rows)
    row_start = np.concatenate([[0], np.cumsum(padded)[:-1]])
    rows = int(padded.sum())
    # row of each observation: its image's block start + its rank inside the image
    rank = np.arange(len(obs_image)) - np.concatenate([[0], np.cumsum(num_obs)[:-1]])[obs_image]
    row = row_start[obs_image] + rank

    root = zarr.open_group(store=store, mode="w")
    root.attrs["pixloc_map"] = {
        "version": VERSION, "chunk_rows": chunk_rows, "shard_rows": shard_rows, "num_images": len(names),
        "num_points": len(scene.points), "num_observations": int(len(obs_point)), "num_rows": rows,
        "source": source or {}}
    meta = root.attrs["pixloc_map"]
    for name, values in _image_columns(scene.images, row_start, num_obs).items():
        new_array(root, name, values.shape, values.shape, values.dtype if values.dtype.kind != "U" else str)[:] = values
    P = len(scene.points)
    new_array(root, "points/xyz", (P, 3), (max(P, 1), 3), "float64")[:] = scene.points
    new_array(root, "points/track_length", (P,), (max(P, 1),), "int32")[:] = scene.track_length
    new_array(root, "points/source_id", (P,), (max(P, 1),), "int64")[:] = scene.point_ids
    point = np.full(rows, -1, dtype=np.int64)
    point[row] = obs_point
    xy = np.full((rows, 2), np.nan, dtype=np.float32)
    xy[row] = obs_xy
    new_rows_array(root, "observations/point", rows, None, "int64", meta, fill_value=-1)[:] = point
    new_rows_array(root, "observations/xy", rows, 2, "float32", meta, fill_value=np.nan)[:] = xy
    return root


def extend_store(root: zarr.Group, scene: Scene) -> List[int]:
    """Add the images of ``scene`` that the store does not have (a new mapping session), with their
    observations: of the store's points where the scene names them by the same source id (a COLMAP
    model extended with the new images), of new points otherwise. Stored images, points and rows
    are kept as they are; new rows go after them, in whole shards; every feature group gets the
    new images as pending. The attributes are written last: a store interrupted here is still the
    map it was (``check_layout`` allows longer arrays) and the add runs again. Returns the new
    images' indices."""
    meta = dict(root.attrs["pixloc_map"])
    I, P, R, shard = meta["num_images"], meta["num_points"], meta["num_rows"], meta["shard_rows"]  # noqa: E741
    stored = {str(n): i for i, n in enumerate(read(root, "images/name", meta))}
    T_stored = read(root, "images/cam_from_world", meta)
    for k, im in enumerate(scene.images):
        if im.name in stored:
            if not np.allclose(_flat_pose(im.cam_from_world), T_stored[stored[im.name]], atol=1e-6):
                raise StoreError(f"Image {im.name} has another pose than in the store: adding images keeps the "
                                 "stored ones as they are (rebuild with --overwrite to change them).")
    new = [k for k, im in enumerate(scene.images) if im.name not in stored]
    ids = {int(s): i for i, s in enumerate(read(root, "points/source_id", meta)) if s >= 0}
    sel = np.isin(scene.obs_image, new)
    obs_image, obs_point, obs_xy = scene.obs_image[sel], scene.obs_point[sel], scene.obs_xy[sel]
    used = np.unique(obs_point)
    src = scene.point_ids[used]
    known = np.array([s >= 0 and int(s) in ids for s in src], bool)
    index = np.empty(len(scene.points), np.int64)
    index[used[known]] = [ids[int(s)] for s in src[known]]
    fresh = used[~known]
    index[fresh] = P + np.arange(len(fresh))
    local = np.full(len(scene.images), -1, np.int64)
    local[new] = I + np.arange(len(new))
    obs_image = local[obs_image]
    obs_point = index[obs_point]
    order = np.lexsort((obs_point, obs_image))
    obs_image, obs_point, obs_xy = obs_image[order], obs_point[order], obs_xy[order]
    num_obs = np.bincount(obs_image - I, minlength=len(new))
    padded = padded_rows(num_obs, shard)
    row_start = R + np.concatenate([[0], np.cumsum(padded)[:-1]])
    rank = np.arange(len(obs_image)) - np.concatenate([[0], np.cumsum(num_obs)[:-1]])[obs_image - I]
    row = row_start[obs_image - I] + rank
    I2, P2, R2 = I + len(new), P + len(fresh), R + int(padded.sum())  # noqa: E741
    for name, values in _image_columns([scene.images[k] for k in new], row_start, num_obs).items():
        root[name].resize((I2,) + root[name].shape[1:])
        root[name][I:I2] = values
    for name, values in (("points/xyz", scene.points[fresh]), ("points/source_id", scene.point_ids[fresh])):
        root[name].resize((P2,) + root[name].shape[1:])
        root[name][P:P2] = values
    # from the committed rows, not the stored track lengths: an interrupted add may have written them
    stored_points = read(root, "observations/point", meta)
    track = (np.bincount(stored_points[stored_points >= 0], minlength=P2)
             + np.bincount(obs_point, minlength=P2)).astype(np.int32)
    root["points/track_length"].resize((P2,))
    root["points/track_length"][:] = track
    point = np.full(R2 - R, -1, np.int64)
    point[row - R] = obs_point
    xy = np.full((R2 - R, 2), np.nan, np.float32)
    xy[row - R] = obs_xy
    for name, values in (("observations/point", point), ("observations/xy", xy)):
        root[name].resize((R2,) + root[name].shape[1:])
        root[name][R:R2] = values
    if "features" in root:
        for _, group in root["features"].groups():
            unconsolidate(group)
            for name in ("status", "reason", "global"):
                group[name].resize((I2,) + group[name].shape[1:])
                if name != "global":
                    group[name][I:I2] = PENDING if name == "status" else ""
            for array in feature_row_arrays(group):
                array.resize((R2,) + array.shape[1:])
    meta.update(num_images=I2, num_points=P2, num_observations=meta["num_observations"] + len(obs_image),
                num_rows=R2, scene_observations=len(scene.obs_point))
    root.attrs["pixloc_map"] = meta  # the commit point
    return list(range(I, I2))
