"""Where a map store lives: a local folder, or an object-storage URL (``s3://bucket/map.zarr``,
``gs://``, any fsspec protocol whose package is installed; ``file://`` is a local folder).

This module is the one place that turns a store's name into storage: every store is opened
through ``zarr_store``, so a URL works wherever a path does, and the few operations zarr does
not do (does it exist, what does it hold, when did it change) are here, for both kinds.

Credentials and endpoints come from the usual environment (``AWS_ACCESS_KEY_ID``,
``AWS_SECRET_ACCESS_KEY``, ``AWS_ENDPOINT_URL``, ...) and, for the rest, from
``PIXLOC_STORAGE_OPTIONS``: a JSON object of fsspec storage options (``--storage-options`` sets
it; Dask workers that pixloc starts inherit it, workers started by hand need it in their
environment, see docs/cluster.md).
"""

import contextlib
import logging
import os
import re
import stat
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, FrozenSet, List, Optional, Tuple, Union

from zarr.storage import WrapperStore

# StoreObjectError is raised through this module's stores too: callers catch it as location's
from pipeline.runtime import STORAGE_OPTIONS_ENV, SettingError, current, environment  # noqa: F401
from pipeline.store.local_files import LocalObjects, StoreObjectError, checked_metadata, read_file  # noqa: F401

logger = logging.getLogger(__name__)
# fsspec caches directory listings per process; a store that other processes write (build
# workers, a build while localizing) must be listed afresh
_FRESH = {"s3": {"use_listings_cache": False}, "gs": {"cache_timeout": 0}}
# s3fs asks an object's size (a HEAD, one more round trip) before reading it whole, to split a large
# one into concurrent parts; a store's objects are a few MiB
_WHOLE = {"s3": {"max_concurrency": 1}}
# An endpoint that accepts connections and never answers stops a command within these bounds, not
# botocore's 60 s read timeout times its and s3fs's retries (7 minutes): connect within 10 s, each
# read within 20 s, two attempts of a request, so about 45 s (docs/cluster.md). ``--storage-options``
# overrides them, e.g. '{"config_kwargs": {"read_timeout": 120}}'.
TIMEOUTS = {"s3": {"config_kwargs": {"connect_timeout": 10, "read_timeout": 20,
                                     "retries": {"total_max_attempts": 2, "mode": "standard"}}}}
WAIT_NOTE_S = 5.0  # a remote call still waiting after this long is said, with what it waits for


def _options(protocol: str, *layers: Dict[str, Any]) -> Dict[str, Any]:
    """fsspec storage options: ``TIMEOUTS`` of the protocol, then ``layers``, then the user's
    (``storage_options``); ``config_kwargs`` merged key by key, so that a user's read timeout keeps
    the default connect timeout."""
    out: Dict[str, Any] = {}
    for layer in (TIMEOUTS.get(protocol, {}), *layers, storage_options()):
        for key, value in layer.items():
            out[key] = {**out[key], **value} if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _bounded(fs) -> None:
    """s3fs retries a timed-out request 5 times on top of botocore's own retries: once here."""
    protocols = fs.protocol if isinstance(fs.protocol, (tuple, list)) else (fs.protocol,)
    if "s3" in protocols:
        fs.retries = 1


StoreName = Union[str, Path]


class StoreLocationError(ValueError):
    """A store URL or storage options that cannot be used (named, with the fix)."""


class MissingStore(FileNotFoundError):
    """Nothing is stored under the name."""


class NamedMetadata(WrapperStore):
    """A writable remote store whose metadata reads go through ``checked_metadata`` and whose
    writes' errors name the store (a bucket that does not exist, a timeout: ``remote_error``)."""

    async def get(self, key, prototype, byte_range=None):
        data = await self._store.get(key, prototype, byte_range)
        return data if byte_range is not None else checked_metadata(url_of(self._store), key, data)

    async def set(self, key, value):
        try:
            return await self._store.set(key, value)
        except Exception as e:  # noqa: BLE001 - re-raised, named where it is the storage's
            raise remote_error(url_of(self._store), e) from None


def url_of(store) -> str:
    """The URL of an fsspec-backed zarr store (its repr names the filesystem class, not the URL)."""
    fs = getattr(store, "fs", None)
    if fs is None:
        return str(store)
    protocol = fs.protocol[0] if isinstance(fs.protocol, (tuple, list)) else fs.protocol
    return f"{protocol}://{store.path}"


def is_url(store: StoreName) -> bool:
    """Whether ``store`` names object storage (a URL other than ``file://``)."""
    return "://" in str(store) and not str(store).startswith("file://")


def normalize(store: StoreName) -> str:
    """The name a job records: an absolute local path, or the URL without a trailing slash."""
    text = str(store)
    if text.startswith("file://"):
        text = text[len("file://"):]
    if is_url(text):
        return text.rstrip("/")
    return str(Path(text).expanduser().resolve())


def storage_options() -> Dict[str, Any]:
    """The fsspec storage options of the run (``pipeline.runtime.RunSettings``: --storage-options,
    else ``PIXLOC_STORAGE_OPTIONS``, a JSON object), else {}."""
    try:
        return current().options()
    except SettingError as e:
        raise StoreLocationError(str(e)) from None


# packages whose errors (missing credentials, an endpoint that cannot be reached) are not OSErrors
_STORAGE_PACKAGES = ("botocore", "aiobotocore", "google", "azure")


_waiting = threading.local()


@contextlib.contextmanager
def waiting_note(url: StoreName, what: str = "an answer"):
    """Log, once the block has waited ``WAIT_NOTE_S`` seconds, what it is waiting for: a command
    that talks to a silent endpoint says so long before its timeouts stop it."""
    if getattr(_waiting, "on", False):  # an outer block says it already
        yield
        return

    def note():
        endpoint = storage_options().get("endpoint_url") or environment("AWS_ENDPOINT_URL") or "its endpoint"
        read = _options(normalize(url).split("://", 1)[0]).get("config_kwargs", {})
        logger.warning("Still waiting for %s from %s (%s) after %.0f s; the command stops after the storage "
                       "timeouts (connect %s s, read %s s per request; --storage-options config_kwargs)", what,
                       normalize(url), endpoint, WAIT_NOTE_S, read.get("connect_timeout", "?"),
                       read.get("read_timeout", "?"))
    timer = threading.Timer(WAIT_NOTE_S, note)
    timer.daemon = True
    timer.start()
    _waiting.on = True
    try:
        yield
    finally:
        _waiting.on = False
        timer.cancel()


def _is_timeout(e: BaseException) -> bool:
    return isinstance(e, TimeoutError) or "Timeout" in type(e).__name__


@contextlib.contextmanager
def _remote(url: StoreName):
    """The calls of this module on a remote store: a storage package's error that is not an OSError
    (botocore's NoCredentialsError ...), and a timeout, become a StoreLocationError naming the store
    and where its access comes from, as a bad input, not a traceback."""
    try:
        with waiting_note(url):
            yield
    except Exception as e:  # noqa: BLE001 - only the storage packages' and timeouts are turned, the rest re-raised
        raise remote_error(url, e) from None


def remote_error(url: StoreName, e: BaseException) -> BaseException:
    """``e``, or a StoreLocationError naming the store for a storage package's error or a timeout."""
    if _is_timeout(e):
        return StoreLocationError(f"{normalize(url)}: no answer within the storage timeouts ({type(e).__name__}: "
                                  f"{e}); is the endpoint up? (--storage-options config_kwargs sets the timeouts, "
                                  "docs/cluster.md)")
    if isinstance(e, FileNotFoundError) and "bucket" in str(e).lower():
        return StoreLocationError(f"{normalize(url)}: {e}")
    if isinstance(e, (OSError, ValueError)) or type(e).__module__.split(".")[0] not in _STORAGE_PACKAGES:
        return e
    return StoreLocationError(f"{normalize(url)}: {type(e).__name__}: {e}. Credentials and endpoint come from the "
                              "usual environment (for s3://: AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, "
                              "AWS_ENDPOINT_URL ...) or --storage-options (docs/cluster.md).")


def filesystem(store: StoreName) -> Tuple[Any, str]:
    """(fsspec filesystem, path in it) of a store URL."""
    import fsspec

    url = normalize(store)
    protocol = url.split("://", 1)[0]
    try:
        fs, path = fsspec.core.url_to_fs(url, **_options(protocol, _FRESH.get(protocol, {})))
        _bounded(fs)
    except ImportError as e:
        raise StoreLocationError(f"{url}: the {protocol}:// protocol needs a package that is not installed "
                                 f"({e}); for s3:// install s3fs (pip install 'pixloc-at-scale[s3]').") from None
    except ValueError as e:  # an unknown protocol
        raise StoreLocationError(f"{url}: {e}") from None
    return fs, path


def zarr_store(store: StoreName, read_only: bool = False, must_exist: bool = False):
    """The zarr store of a local folder or a URL (the latter through fsspec, asynchronously: zarr
    drives it from its own event loop, apart from the filesystem this module's calls use);
    ``must_exist``: MissingStore where nothing is stored under the name."""
    from zarr.storage import FsspecStore

    if must_exist and not exists(store):
        raise MissingStore(str(store))
    if not is_url(store):
        return LocalObjects(normalize(store), read_only=read_only)
    url = normalize(store)
    protocol = url.split("://", 1)[0]
    options = _options(protocol, _FRESH.get(protocol, {}), _WHOLE.get(protocol, {}))
    try:
        remote = FsspecStore.from_url(url, storage_options=options, read_only=read_only)
        _bounded(remote.fs)
        return WholeObjects(remote) if read_only else NamedMetadata(remote)
    except ImportError as e:
        raise StoreLocationError(f"{url}: the protocol needs a package that is not installed ({e}); for s3:// "
                                 "install s3fs (pip install 'pixloc-at-scale[s3]').") from None


class WholeObjects(WrapperStore):
    """A remote store, read an object at a time: zarr reads a shard as ranges (its index, then each
    chunk), each a round trip to object storage; here the first range fetches the whole object
    (one GET, concurrent requests for it share it), and the others are served from memory. The
    objects read last are kept, up to ``max_bytes``; ``exists`` and ``getsize`` are answered from
    the same fetch (a reader checks an object before reading it). For read-only stores only: it
    does not see other processes' writes (readers reopen a rewritten store, ``stamp``)."""

    def __init__(self, store, max_bytes: int = 256 * 2**20):
        super().__init__(store)
        self.max_bytes = max_bytes
        self._objects: "OrderedDict[str, Any]" = OrderedDict()
        self._bytes = 0
        self._pending: Dict[str, Any] = {}

    def _with_store(self, store):
        return type(self)(store, self.max_bytes)

    def clear(self) -> None:
        """Forget the objects kept."""
        self._objects.clear()
        self._bytes = 0

    async def _whole(self, key: str, prototype):
        """The object ``key`` (a zarr Buffer), or None if it is absent."""
        import asyncio

        if key in self._objects:
            self._objects.move_to_end(key)
            return self._objects[key]
        if key in self._pending:  # being fetched for another read
            return await asyncio.shield(self._pending[key])
        done = asyncio.get_running_loop().create_future()
        self._pending[key] = done
        try:
            data = await self._store.get(key, prototype)
        except BaseException as e:
            if isinstance(e, Exception):
                done.set_exception(e)
                done.exception()  # retrieved: raised to the caller here, not logged as never retrieved
            else:  # cancelled
                done.cancel()
            raise
        finally:
            self._pending.pop(key, None)
        done.set_result(data)
        if data is not None:
            self._objects[key] = data
            self._bytes += len(data)
            while len(self._objects) > 1 and self._bytes > self.max_bytes:
                self._bytes -= len(self._objects.popitem(last=False)[1])
        return data

    async def get(self, key, prototype, byte_range=None):
        from zarr.abc.store import OffsetByteRequest, RangeByteRequest, SuffixByteRequest

        data = await self._whole(key, prototype)
        if data is None or byte_range is None:
            return checked_metadata(url_of(self._store), key, data)
        if isinstance(byte_range, RangeByteRequest):
            return data[byte_range.start:byte_range.end]
        if isinstance(byte_range, OffsetByteRequest):
            return data[byte_range.offset:]
        if isinstance(byte_range, SuffixByteRequest):
            return data[max(len(data) - byte_range.suffix, 0):]
        raise TypeError(f"unexpected byte range {byte_range!r}")

    async def exists(self, key: str) -> bool:
        from zarr.core.buffer import default_buffer_prototype

        return await self._whole(key, default_buffer_prototype()) is not None

    async def getsize(self, key: str) -> int:
        from zarr.core.buffer import default_buffer_prototype

        data = await self._whole(key, default_buffer_prototype())
        if data is None:
            raise FileNotFoundError(key)
        return len(data)


def exists(store: StoreName) -> bool:
    """Whether anything is stored under ``store``."""
    if not is_url(store):
        return Path(normalize(store)).exists()
    fs, path = filesystem(store)
    with _remote(store):
        return bool(fs.exists(path))


def read_bytes(store: StoreName, key: str) -> Optional[bytes]:
    """The object ``key`` under ``store`` (``zarr.json``, ``features/x/zarr.json``), None if absent."""
    if not is_url(store):
        return read_file(Path(normalize(store)) / key)
    fs, path = filesystem(store)
    try:
        with _remote(store):
            return fs.cat_file(f"{path}/{key}")
    except FileNotFoundError:
        return None


def stamp(store: StoreName, keys) -> Tuple:
    """Something that changes when any of ``keys`` under ``store`` is rewritten: modification times
    of local files (no read), the objects' contents for a URL (small metadata objects: one GET each)."""
    if not is_url(store):
        files = [Path(normalize(store)) / key for key in keys]
        return tuple(f.stat().st_mtime_ns if f.exists() else None for f in files)
    return tuple(read_bytes(store, key) for key in keys)


@dataclass(frozen=True)
class Contents:
    """What is stored under a name: a single file (or object), or the names directly under it."""

    is_file: bool
    entries: FrozenSet[str]
    header: Optional[bytes]  # its zarr.json, if any


def contents(store: StoreName) -> Optional[Contents]:
    """What is stored under ``store``, None where nothing is."""
    if not exists(store):
        return None
    if not is_url(store):
        path = Path(normalize(store))
        if path.is_file():
            return Contents(True, frozenset(), None)
        return Contents(False, frozenset(p.name for p in path.iterdir()), read_bytes(store, "zarr.json"))
    fs, path = filesystem(store)
    with _remote(store):
        if fs.isfile(path):
            return Contents(True, frozenset(), None)
        names = frozenset(str(p).rstrip("/").rsplit("/", 1)[-1] for p in fs.ls(path, detail=False))
    return Contents(False, names, read_bytes(store, "zarr.json"))


# what zarr writes under a store: metadata, chunk (or shard) files under an array's ``c/`` folder,
# and its atomic writes' temporaries (``NAME.<uuid hex>.partial``, left by a killed write)
_WRITTEN = re.compile(r"(.*/)?zarr\.json|.+/c(/\d+)+|.*\.[0-9a-f]{32}\.partial")


def foreign_files(store: StoreName, limit: int = 20) -> List[str]:
    """Up to ``limit`` entries under ``store`` (keys relative to it) that zarr did not write: a
    user's file, a localization output, a symlink, a FIFO. Links are not followed."""
    found: List[str] = []
    if not is_url(store):
        root = Path(normalize(store))
        for folder, dirs, files in os.walk(root):
            here = Path(folder)
            for name in files + [d for d in dirs if (here / d).is_symlink()]:
                key = (here / name).relative_to(root).as_posix()
                if not _WRITTEN.fullmatch(key) or not stat.S_ISREG((here / name).lstat().st_mode):
                    found.append(key)
                    if len(found) >= limit:
                        return found
        return found
    fs, path = filesystem(store)
    with _remote(store):
        keys = fs.find(path)
    return [k for k in (str(k)[len(path):].lstrip("/") for k in keys) if not _WRITTEN.fullmatch(k)][:limit]


def enclosing_store(path) -> Optional[Path]:
    """The map store that local ``path`` lies in (or is), None if it is in none."""
    for folder in [Path(path).expanduser().resolve(), *Path(path).expanduser().resolve().parents]:
        header = folder / "zarr.json"
        try:
            if header.is_file() and b"pixloc_map" in (read_file(header) or b""):
                return folder
        except StoreObjectError:
            continue
    return None


def total_bytes(store: StoreName) -> int:
    """The bytes stored under ``store``."""
    if not is_url(store):  # regular files only (lstat: a symlink to a device is not its size)
        return sum(f.lstat().st_size for f in Path(normalize(store)).rglob("*") if stat.S_ISREG(f.lstat().st_mode))
    fs, path = filesystem(store)
    with _remote(store):
        return int(fs.du(path))


def work_dir(store: StoreName) -> Path:
    """The default work folder of a build (SfM files, logs, the lock): ``NAME.work`` beside a local
    store; in the current folder for a URL (a build's work folder stays local to the build)."""
    name = normalize(store)
    if not is_url(name):
        return Path(name).with_suffix(".work")
    return Path.cwd() / Path(name.split("://", 1)[1].rstrip("/")).with_suffix(".work").name
