"""The one reader of a local map store's files: every read of the build, the check, the repair and
localization goes through ``LocalObjects`` (what ``pipeline.store.location.zarr_store`` opens for a
folder). It refuses anything that is not a regular file, or of implausible size, before a byte is
read, opens files so that nothing blocks, and names metadata that is not JSON (``checked_metadata``,
also applied to remote stores)."""

import json
import os
import stat
from pathlib import Path
from typing import Optional

from zarr.storage import LocalStore


class StoreObjectError(ValueError):
    """An object of a store that cannot be what it should be, named: an entry of a local store that
    is not a regular file (a symlink to a device, a FIFO, a socket), one of implausible size, or
    metadata (``zarr.json``) that is not JSON."""


# The largest object read whole: a store's objects are shards of one image's rows, single chunks
# and metadata (docs/map_store.md), a few MiB each; the largest, a consolidated copy of every
# image's global descriptor, is 27 MB at 6,697 images. A larger one is damage, not data.
MAX_OBJECT_BYTES = 2**31
MAX_METADATA_BYTES = 64 * 2**20


def checked_metadata(where: str, key: str, data):
    """``data`` (a zarr Buffer or bytes) of object ``key``; a ``zarr.json`` that is too large or not
    JSON is a StoreObjectError naming it, never zarr's bare "Expecting value"."""
    if data is None or not key.endswith("zarr.json"):
        return data
    raw = data.to_bytes() if hasattr(data, "to_bytes") else bytes(data)
    if len(raw) > MAX_METADATA_BYTES:
        raise StoreObjectError(f"{where}/{key}: {len(raw)} bytes of metadata (at most {MAX_METADATA_BYTES}): "
                               "not a store's zarr.json (damaged?); run pixloc check-store")
    try:
        value = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise StoreObjectError(f"{where}/{key}: metadata that is not JSON ({e}): truncated or damaged; rebuild "
                               "the store (build-map --overwrite), or restore the file") from None
    if not isinstance(value, dict):
        raise StoreObjectError(f"{where}/{key}: metadata is a JSON {type(value).__name__}, not an object: "
                               "damaged; rebuild the store (build-map --overwrite)")
    return data


def read_file(path: Path, byte_range=None) -> Optional[bytes]:
    """The bytes of store file ``path`` (``byte_range``: a zarr ByteRequest), None if it is absent.
    Anything but a regular file is refused before a byte is read, and opened so that nothing blocks:
    a symlink to /dev/zero would be read without end, a FIFO would wait for a writer forever."""
    from zarr.abc.store import OffsetByteRequest, RangeByteRequest, SuffixByteRequest

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as e:  # a symlink loop, no permission, a socket (ENXIO)
        raise StoreObjectError(f"{path}: cannot be opened ({e.strerror or e}); run pixloc check-store") from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode):  # checked before fdopen, which refuses a folder with its own error
        os.close(fd)
        kind = {stat.S_ISCHR: "a character device", stat.S_ISBLK: "a block device", stat.S_ISFIFO: "a FIFO",
                stat.S_ISSOCK: "a socket", stat.S_ISDIR: "a folder"}
        what = next((name for test, name in kind.items() if test(info.st_mode)), "not a regular file")
        link = f" (a symlink to {os.readlink(path)})" if path.is_symlink() else ""
        raise StoreObjectError(f"{path}: {what}{link}, not a regular file: a store holds only files it wrote; "
                               "run pixloc check-store")
    with os.fdopen(fd, "rb") as f:
        size = info.st_size
        if isinstance(byte_range, RangeByteRequest):
            start, stop = byte_range.start, min(byte_range.end, size)
        elif isinstance(byte_range, OffsetByteRequest):
            start, stop = byte_range.offset, size
        elif isinstance(byte_range, SuffixByteRequest):
            start, stop = max(0, size - byte_range.suffix), size
        elif byte_range is None:
            start, stop = 0, size
        else:
            raise TypeError(f"unexpected byte range {byte_range!r}")
        if stop - start > MAX_OBJECT_BYTES:
            raise StoreObjectError(f"{path}: {size} bytes, more than any object of a map store "
                                   f"({MAX_OBJECT_BYTES}): damaged; run pixloc check-store")
        f.seek(start)
        return f.read(max(stop - start, 0))


def regular_size(path: Path) -> Optional[int]:
    """The size of ``path`` if it is a regular file (a symlink to one too), else None."""
    try:
        info = path.stat()
    except OSError:  # absent, a symlink loop, no permission: no file to read
        return None
    return info.st_size if stat.S_ISREG(info.st_mode) else None


class LocalObjects(LocalStore):
    """A local store whose every read goes through ``read_file`` (regular files of plausible size,
    never blocking) and ``checked_metadata``: what ``zarr_store`` opens for a folder, for the
    build, the check, the repair and localization alike."""

    async def get(self, key, prototype=None, byte_range=None):
        import asyncio

        from zarr.core.buffer import default_buffer_prototype

        if not self._is_open:
            await self._open()
        prototype = prototype or default_buffer_prototype()
        data = await asyncio.to_thread(read_file, self.root / key, byte_range)
        return None if data is None else checked_metadata(str(self.root), key, prototype.buffer.from_bytes(data))

    async def get_partial_values(self, prototype, key_ranges):
        import asyncio

        return await asyncio.gather(*(self.get(key, prototype, byte_range) for key, byte_range in key_ranges))

    def get_sync(self, key, *, prototype=None, byte_range=None):
        from zarr.core.buffer import default_buffer_prototype

        self._ensure_open_sync()
        data = read_file(self.root / key, byte_range)
        prototype = prototype or default_buffer_prototype()
        return None if data is None else checked_metadata(str(self.root), key, prototype.buffer.from_bytes(data))

    async def exists(self, key: str) -> bool:
        return regular_size(self.root / key) is not None

    async def getsize(self, key: str) -> int:
        size = regular_size(self.root / key)
        if size is None:
            raise FileNotFoundError(f"{self.root / key} is absent or not a regular file")
        return size
