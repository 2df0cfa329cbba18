"""Process-level settings of pipeline tasks: the one module that reads the environment.

``RunSettings`` are the settings of a run that are not its job's: the pixel limit of images and the
storage options of a remote store. The command line makes them from its flags and the environment
(``RunSettings.from_environment``), installs them in its process (``install``), and every task it
submits carries them to its worker (``InSettings``): a worker of an external scheduler, which has
none of the command's environment, runs with the same settings. Code reads them with ``current()``.
"""

import ctypes
import ctypes.util
import functools
import json
import logging
import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, Optional

import torch

logger = logging.getLogger(__name__)

DEFAULT_MAX_IMAGE_PIXELS = 150_000_000
MAX_PIXELS_ENV = "PIXLOC_MAX_IMAGE_PIXELS"
STORAGE_OPTIONS_ENV = "PIXLOC_STORAGE_OPTIONS"
NO_KERNELS_ENV = "PIXLOC_NO_KERNELS"  # 1: the torch code everywhere (a comparison, a platform numba lacks)
POISON_ENV = "PIXLOC_POISON_UNDECODED"  # 1 (the test suite's): feature-map cells not decoded hold NaN


class SettingError(ValueError):
    """A run setting that cannot be used, naming where it came from."""


@dataclass(frozen=True)
class RunSettings:
    """max_image_pixels: images with more pixels are refused before they are decoded (a 2 MB PNG can
    declare 30000 x 30000); storage_options: fsspec options of remote stores (a JSON object's text,
    merged over ``pipeline.store.location``'s defaults)."""

    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS
    storage_options: str = ""

    def __post_init__(self):
        if not isinstance(self.max_image_pixels, int) or self.max_image_pixels < 1:
            raise SettingError(f"the pixel limit must be a positive number of pixels, not {self.max_image_pixels!r}")
        self.options()  # refused now when it is not a JSON object

    def options(self) -> Dict[str, Any]:
        """The storage options as a dict ({} where none are given)."""
        text = self.storage_options.strip()
        if not text:
            return {}
        try:
            options = json.loads(text)
        except json.JSONDecodeError as e:
            raise SettingError(f"--storage-options ({STORAGE_OPTIONS_ENV}) is not JSON: {e}") from None
        if not isinstance(options, dict):
            raise SettingError(f"--storage-options ({STORAGE_OPTIONS_ENV}) must be a JSON object, "
                               f"not {type(options).__name__}.")
        return options

    @classmethod
    def from_environment(cls, max_image_pixels: Optional[int] = None,
                         storage_options: Optional[str] = None) -> "RunSettings":
        """The settings given (a command's flags), else those of the environment
        (``PIXLOC_MAX_IMAGE_PIXELS``, ``PIXLOC_STORAGE_OPTIONS``), else the defaults."""
        if max_image_pixels is None:
            value = os.environ.get(MAX_PIXELS_ENV, "").strip()
            try:
                max_image_pixels = int(float(value)) if value else DEFAULT_MAX_IMAGE_PIXELS
            except ValueError:
                raise SettingError(f"{MAX_PIXELS_ENV}={value!r} is not a number of pixels") from None
            if max_image_pixels < 1:
                raise SettingError(f"{MAX_PIXELS_ENV}={value!r} must be positive")
        if storage_options is None:
            storage_options = os.environ.get(STORAGE_OPTIONS_ENV, "")
        return cls(max_image_pixels, storage_options)


_installed: Optional[RunSettings] = None


def install(settings: RunSettings) -> None:
    """Make ``settings`` this process's (a command at its start, a worker before each task)."""
    global _installed
    _installed = settings


@contextmanager
def using(settings: RunSettings) -> Iterator[None]:
    """``install`` for the block, then the settings installed before (a command run in a process
    that goes on, as a test's)."""
    global _installed
    before = _installed
    install(settings)
    try:
        yield
    finally:
        _installed = before


def current() -> RunSettings:
    """The settings installed in this process, else the environment's."""
    return _installed if _installed is not None else RunSettings.from_environment()


@dataclass(frozen=True)
class InSettings:
    """A task function that runs with the settings of the process that submitted it (picklable:
    Dask sends it to the worker with its arguments)."""

    fn: Callable
    settings: RunSettings

    def __call__(self, *args, **kwargs):
        install(self.settings)
        return self.fn(*args, **kwargs)


def environment(name: str) -> Optional[str]:
    """A variable of the environment that a library reads itself (for messages: AWS_ENDPOINT_URL)."""
    return os.environ.get(name)


def kernels_disabled() -> bool:
    """``PIXLOC_NO_KERNELS`` set (not 0): the LM's torch code everywhere, no compiled kernels."""
    return os.environ.get(NO_KERNELS_ENV, "") not in ("", "0")


def poison_undecoded() -> bool:
    """``PIXLOC_POISON_UNDECODED`` is 1: feature-map cells that a tiled decode leaves out hold NaN, so
    that a read that bypassed the decode shows (the test suite sets it, for its worker processes too)."""
    return os.environ.get(POISON_ENV) == "1"

# glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
_MMAP_THRESHOLD_MAX, _MMAP_MAX_DEFAULT = 32 * 1024 * 1024, 65536
_NEVER_TRIM = -1  # mallopt(3): "Setting M_TRIM_THRESHOLD to -1 disables trimming completely"
USER_SETTINGS = ("MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_")  # a user's choice, left alone


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` torch threads, then restore the previous count.

    Tasks of the Dask graphs use one thread: parallelism comes from running several
    tasks, and convolution results depend on the thread count, so one thread makes
    outputs identical whatever executor ran them.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@functools.lru_cache(maxsize=1)
def keep_freed_memory() -> bool:
    """Let glibc reuse the large blocks this process frees instead of mapping fresh ones.

    A query at 1024 px allocates and frees tensors of 20 to 90 MB dozens of times. glibc serves
    every block over 32 MiB (the largest mmap threshold its dynamic rule reaches) with a new
    mmap whose pages fault in on first write, and Dask's nannies, which start workers with
    ``MALLOC_TRIM_THRESHOLD_=65536``, make that every block over 128 KiB. With mmap off and no
    trimming, freed blocks stay in the heap and are reused: a fifth of a query's CPU time at
    Cambridge settings (docs/benchmarks.md, "The CPU query at Cambridge settings"). The price: a
    process's resident memory stays at its high-water mark (1.37 GB after three 1024 px queries,
    against a peak of 1.20 GB and 0.66 GB held before) instead of falling between queries. A
    user's ``MALLOC_MMAP_MAX_`` or ``MALLOC_MMAP_THRESHOLD_`` is left alone. Returns whether it
    changed anything (not on other C libraries).
    """
    if any(name in os.environ for name in USER_SETTINGS):
        return False
    ok = set_malloc(keep_freed=True)
    logger.debug("malloc: freed memory kept for reuse: %s", ok)
    return ok


def set_malloc(keep_freed: bool) -> bool:
    """glibc's large blocks: freed ones kept in the heap for reuse (``keep_freed_memory``), or
    each mapped afresh above 32 MiB and the heap trimmed above 64 MiB (what a Dask worker ran
    with before, and what glibc's dynamic rule reaches). False where the C library is not glibc."""
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c")).mallopt
    except (OSError, AttributeError, TypeError):  # not glibc
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    if keep_freed:
        settings = ((_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, _NEVER_TRIM))
    else:
        settings = ((_M_MMAP_MAX, _MMAP_MAX_DEFAULT), (_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX),
                    (_M_TRIM_THRESHOLD, 2 * _MMAP_THRESHOLD_MAX))
    return all(mallopt(key, value) == 1 for key, value in settings)


BFLOAT16_FLAGS = ("avx512_bf16", "amx_bf16")  # /proc/cpuinfo: the x86 instructions that compute bfloat16


def native_bfloat16(cpuinfo: Optional[str] = None) -> Optional[bool]:
    """Whether this CPU computes bfloat16 natively (one of ``BFLOAT16_FLAGS`` among the flags of
    /proc/cpuinfo, or of ``cpuinfo``); None where that cannot be told (no /proc/cpuinfo, no flags line:
    not Linux on x86). Without it a bfloat16 network pass is emulated and slower than float32's."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return None
    flags = [line.split(":", 1)[1].split() for line in cpuinfo.splitlines() if line.startswith("flags")]
    if not flags:
        return None
    return any(flag in BFLOAT16_FLAGS for flag in flags[0])


def shared_folder() -> Path:
    """The shared data folder (real scenes, oracle outputs): ``PIXLOC_SHARED``, else ``../shared``."""
    return Path(os.environ.get("PIXLOC_SHARED", "../shared"))


def subprocess_environment(**extra: str) -> Dict[str, str]:
    """This process's environment with ``extra`` set, for a process it starts."""
    return {**os.environ, **extra}


def quiet_colmap_logs() -> str:
    """COLMAP's (glog's) minimum log level for this process and those it starts: the environment's
    ``GLOG_minloglevel``, else 1 (warnings and errors only), set in the environment, which glog reads
    when pycolmap loads."""
    return os.environ.setdefault("GLOG_minloglevel", "1")


def set_environment(**values: str) -> None:
    """Set variables that libraries read themselves (a benchmark's S3 credentials for s3fs)."""
    os.environ.update(values)
