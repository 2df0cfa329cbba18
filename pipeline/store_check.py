"""Verify every chunk of a map store: ``pixloc check-store``.

Each chunk is read and decoded, which checks its CRC-32C (and that of its shard's index); a
chunk (or shard: one file) that is corrupt, truncated or missing where it should hold data is
reported with its array and the reference images whose rows it holds.
"""

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, List, Optional

import numpy as np
import zarr

from .feature_groups import check_feature_group
from .store import open_store, read


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

    @property
    def ok(self) -> bool:
        return not self.bad and not self.problems

    def summary(self) -> str:
        lines = [f"{self.path}: {self.arrays} arrays, {self.chunks} chunks, {self.bytes / 2**20:.1f} MiB on disk: "
                 + ("all chunks verified" if self.ok else f"{len(self.bad)} bad chunks, {len(self.problems)} "
                                                         "layout problems")]
        lines += [f"  layout: {p}" for p in self.problems]
        for b in self.bad:
            images = f" (images {', '.join(b.images[:5])}{' ...' if len(b.images) > 5 else ''})" if b.images else ""
            lines.append(f"  bad chunk {b.array} {b.chunk}{images}: {b.error}")
        return "\n".join(lines)


def _arrays(group: zarr.Group, prefix: str = ""):
    for name, array in sorted(group.arrays()):
        yield prefix + name, array
    for name, sub in sorted(group.groups()):
        yield from _arrays(sub, prefix + name + "/")


def check_store(path, progress: Optional[Callable[[str], None]] = None) -> StoreCheck:
    """Read every chunk of every array of the store at ``path``; never raises for a bad chunk."""
    path = Path(path)
    out = StoreCheck(path)
    out.bytes = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    root = open_store(path)  # refuses a bad layout with a clear StoreError
    meta = root.attrs["pixloc_map"]
    names = [str(n) for n in read(root, "images/name")]
    row_start, num_obs = read(root, "images/row_start"), read(root, "images/num_obs")
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
                "status", "reason", "global") and first < n:
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
        for index in itertools.product(*grid):
            out.chunks += 1
            sl = tuple(slice(i * c, min((i + 1) * c, s)) for i, c, s in zip(index, unit, array.shape))
            try:
                array[sl]
            except Exception as e:  # the codec's error names the problem  # noqa: BLE001
                first, last = (sl[0].start, sl[0].stop) if sl else (0, 0)
                out.bad.append(BadChunk(name, index, images_of(name, first, last), f"{type(e).__name__}: {e}"))
    return out
