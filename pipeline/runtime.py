"""Process-level settings of pipeline tasks."""

import ctypes
import ctypes.util
import functools
import logging
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional

import torch

logger = logging.getLogger(__name__)

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
