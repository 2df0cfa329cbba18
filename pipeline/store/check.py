"""Verify every chunk of a map store: ``pixloc check-store``.

Each chunk is read and decoded, which checks its CRC-32C (and that of its shard's index); a
chunk (or shard: one file) that is corrupt, truncated or missing where it should hold data is
reported with its array and the reference images whose rows it holds. Also the store's
fingerprint that localization runs record (``store_fingerprint``).
"""

import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional

import numpy as np
import zarr

from pipeline.store import location
from pipeline.store.layout import (
    DONE,
    FAILED,
    PENDING,
    StoreError,
    check_feature_group,
    consolidated,
    dense,
    image_row_arrays,
    missing_objects,
    open_store,
    read,
    unconsolidate,
)


@dataclass
class BadChunk:
    array: str
    chunk: tuple
    images: List[str]
    error: str


@dataclass
class StoreCheck:
    path: Path
    arrays: int = 0
    chunks: int = 0
    bytes: int = 0
    bad: List[BadChunk] = field(default_factory=list)
    problems: List[str] = field(default_factory=list)
    pending: Dict[str, List[str]] = field(default_factory=dict)  # feature group -> images not built yet

    @property
    def ok(self) -> bool:
        return not self.bad and not self.problems and not any(self.pending.values())

    def bad_images(self) -> List[str]:
        """The images whose features are damaged or missing (``--repair`` has them rebuilt)."""
        return sorted({name for b in self.bad if b.array.startswith("features/") for name in b.images})

    def summary(self) -> str:
        num_pending = sum(len(v) for v in self.pending.values())
        state = ("all chunks verified" if self.ok else
                 ", ".join(f"{n} {what}" for n, what in ((len(self.bad), "bad chunks"), (len(self.problems),
                           "layout problems"), (num_pending, "images pending")) if n))
        lines = [f"{self.path}: {self.arrays} arrays, {self.chunks} chunks, {self.bytes / 2**20:.1f} MiB stored: "
                 + state]
        lines += [f"  layout: {p}" for p in self.problems]
        for key, names in self.pending.items():
            if names:
                lines.append(f"  pending in features/{key}: {len(names)} images not built yet "
                             f"({', '.join(names[:5])}{' ...' if len(names) > 5 else ''}): run the build-map command "
                             "again to finish them")
        for b in self.bad:
            images = f" (images {', '.join(b.images[:5])}{' ...' if len(b.images) > 5 else ''})" if b.images else ""
            lines.append(f"  bad chunk {b.array} {b.chunk}{images}: {_short(b.error)}")
        if self.bad_images():
            lines.append(f"  to fix: pixloc check-store {self.path} --repair marks the {len(self.bad_images())} "
                         "damaged images pending; the same build-map command (with the build's work folder) then "
                         "rebuilds only them")
        if any(not b.array.startswith("features/") for b in self.bad):
            lines.append("  to fix: the damaged arrays hold the map's structure: rebuild the store "
                         "(build-map --overwrite)")
        return "\n".join(lines)


def _short(error: str, limit: int = 320) -> str:
    """A codec's error without the raw bytes it may quote."""
    error = error.splitlines()[0] if error else error
    if "checksum do not match" in error:  # zarr quotes both CRCs as raw bytes
        return "checksum mismatch: the file's bytes changed since they were written (corrupt)"
    return error if len(error) <= limit else error[:limit] + " ..."


def _arrays(group: zarr.Group, prefix: str = ""):
    import warnings

    with warnings.catch_warnings():  # an entry that is not zarr's: a layout problem (``foreign_files``)
        warnings.filterwarnings("ignore", message=".*not recognized as a component of a Zarr hierarchy")
        arrays, groups = sorted(group.arrays()), sorted(group.groups())
    for name, array in arrays:
        yield prefix + name, array
    for name, sub in groups:
        yield from _arrays(sub, prefix + name + "/")


def check_store(path, progress: Optional[Callable[[str], None]] = None) -> StoreCheck:
    """Read every chunk of every array of the store at ``path``; never raises for a bad chunk."""
    out = StoreCheck(path)
    root = open_store(path)  # refuses a bad layout with a clear StoreError
    out.bytes = location.total_bytes(path)
    meta = root.attrs["pixloc_map"]
    try:  # the structure every other check needs: damaged, the store is refused whole
        names = [str(n) for n in read(root, "images/name")]
        row_start, num_obs = read(root, "images/row_start"), read(root, "images/num_obs")
    except Exception as e:  # noqa: BLE001 - the codecs raise many types
        raise StoreError(f"{path}: the map's image arrays cannot be read ({type(e).__name__}: "
                         f"{str(e).splitlines()[0][:120]}): the store is damaged; rebuild it with build-map "
                         "--overwrite") from None
    foreign = location.foreign_files(path)
    if foreign:
        out.problems.append(f"{len(foreign)}{'+' if len(foreign) >= 20 else ''} entries that no build wrote "
                            f"({', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}): a store holds only "
                            "its own files (build-map --overwrite refuses to erase them)")
    if "features" in root:
        for key, group in root["features"].groups():
            try:
                check_feature_group(group, meta, path)
            except ValueError as e:
                out.problems.append(str(e))
    row_end = row_start + np.maximum(num_obs, 1)

    def images_of(array_name: str, first: int, last: int) -> List[str]:
        n = int(meta["num_rows"])
        if array_name.startswith(("observations/", "features/")) and array_name.split("/")[-1] not in (
                "status", "reason", "global", "status_all", "global_all") and first < n:
            hit = (row_start < last) & (row_end > first)
            return [names[i] for i in np.flatnonzero(hit)]
        if first < len(names):
            return names[first:last]
        return []

    for name, array in _arrays(root):
        out.arrays += 1
        if progress:
            progress(name)
        unit = array.shards or array.chunks  # a shard is one file: it is read (and reported) whole
        grid = [range(math.ceil(s / c)) for s, c in zip(array.shape, unit)]
        # arrays whose every chunk holds data: an absent file would be read as fill values
        absent = set(missing_objects(array, slice(0, array.shape[0]))) if dense(name) and array.shape[0] else set()
        for index in itertools.product(*grid):
            out.chunks += 1
            sl = tuple(slice(i * c, min((i + 1) * c, s)) for i, c, s in zip(index, unit, array.shape))
            key = f"{name}/{array.metadata.encode_chunk_key(index)}"
            if key in absent:
                first, last = (sl[0].start, sl[0].stop) if sl else (0, 0)
                out.bad.append(BadChunk(name, index, images_of(name, first, last),
                                        f"missing: {key} is absent or not a file"))
                continue
            try:
                array[sl]
            except Exception as e:  # the codec's error names the problem  # noqa: BLE001
                first, last = (sl[0].start, sl[0].stop) if sl else (0, 0)
                out.bad.append(BadChunk(name, index, images_of(name, first, last), f"{type(e).__name__}: {e}"))
    _check_images(root, meta, names, row_start, num_obs, out)
    return out


def _check_images(root, meta, names, row_start, num_obs, out: StoreCheck) -> None:
    """Every image's observation rows, and the feature rows of every image marked done, are on
    disk as files (zarr would read a missing one as fill values); pending images are listed."""
    def rows(i):
        return slice(int(row_start[i]), int(row_start[i] + num_obs[i]))

    seen = {(b.array, b.chunk) for b in out.bad}

    def report(array, i, missing):
        for key in missing:
            chunk = tuple(int(c) for c in key.rsplit("/c/", 1)[-1].split("/"))
            if (array.path, chunk) not in seen:
                seen.add((array.path, chunk))
                out.bad.append(BadChunk(array.path, chunk, [names[i]], f"missing: {key} is absent or not a file"))

    for array in image_row_arrays(root, None)[:2]:
        for i in range(len(names)):
            report(array, i, missing_objects(array, rows(i)))
    if "features" not in root:
        return
    for key, group in root["features"].groups():
        try:
            status = read(group, "status_all" if consolidated(group, meta) else "status", meta)
        except Exception:  # noqa: BLE001 - reported by the chunk loop
            continue
        out.pending[key] = [names[i] for i in np.flatnonzero(status == PENDING)]
        arrays = image_row_arrays(root, group)[2:]
        for i in np.flatnonzero(status == DONE):
            for array in arrays:
                report(array, int(i), missing_objects(array, rows(int(i))))
            # a done image's descriptor is a unit vector: its chunk is always written
            report(group["global"], int(i), missing_objects(group["global"], slice(int(i), int(i) + 1)))
        if consolidated(group, meta):  # the readers' copies must say what the per-image arrays say
            try:
                differ = np.flatnonzero((read(group, "status", meta) != status) | (
                    read(group, "global", meta) != read(group, "global_all", meta)).any(1))
            except Exception:  # noqa: BLE001 - reported by the chunk loop
                differ = []
            for i in differ:
                out.bad.append(BadChunk(f"{group.path}/status", (int(i),), [names[i]], "the per-image status or "
                                        "descriptor differs from the consolidated copy (a file was lost or replaced)"))


def mark_pending(path, images: List[str]) -> int:
    """Mark ``images`` pending in every feature group where they are done or failed (their files
    are damaged or missing): the next build-map rebuilds them. Returns the count marked."""
    root = open_store(path, mode="r+")
    meta = root.attrs["pixloc_map"]
    index = {str(n): i for i, n in enumerate(read(root, "images/name", meta))}
    marked = 0
    for _, group in root["features"].groups() if "features" in root else []:
        unconsolidate(group)  # the build consolidates again when it is done
        for name in images:
            i = index[name]
            if int(group["status"][i]) in (DONE, FAILED):
                group["reason"][i] = ""
                group["status"][i] = PENDING
                marked += 1
    return marked


def store_fingerprint(path, key: str) -> Dict:
    """What localization results depend on, for ``job.json``: a digest of the map's content (image
    names and poses, points, the map counts) and of feature group ``key`` (its config and model
    digest), and how many of its images are not built yet (``pending``). A store rebuilt from
    other images or with another model gets another digest; finishing a build does not."""
    import hashlib

    root = open_store(path)
    meta = root.attrs["pixloc_map"]
    h = hashlib.sha256(json.dumps({k: meta[k] for k in ("num_images", "num_points", "num_observations")},
                                  sort_keys=True).encode())
    for name in ("images/name", "images/cam_from_world", "points/xyz"):
        values = read(root, name, meta)
        h.update("\n".join(map(str, values)).encode() if values.dtype.kind in "UOT" else
                 np.ascontiguousarray(values).tobytes())
    group = f"features/{key}"
    pending = None
    if group in root:
        attrs = root[group].attrs
        h.update(json.dumps([attrs.get("config"), attrs.get("model_digest"), attrs.get("dims")], sort_keys=True,
                            default=str).encode())
        # a finished build's one-chunk copy: the per-image array is one read per image
        status = read(root[group], "status_all" if consolidated(root[group], meta) else "status", meta)
        pending = int((status == PENDING).sum())
    return {"digest": h.hexdigest()[:16], "features": key, "pending": pending}
