"""Process-level settings of pipeline tasks."""

import ctypes
import ctypes.util
import functools
import logging
import os
from contextlib import contextmanager
from typing import Iterator

import torch

logger = logging.getLogger(__name__)

# glibc mallopt parameters (malloc.h) and the largest mmap threshold its dynamic rule reaches
# on 64-bit systems (DEFAULT_MMAP_THRESHOLD_MAX).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024


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
def restore_malloc_thresholds() -> bool:
    """Give this process glibc's large-allocation behaviour back when ``MALLOC_TRIM_THRESHOLD_`` is set.

    Dask's nannies start workers with ``MALLOC_TRIM_THRESHOLD_=65536``. Setting any malloc
    threshold turns off glibc's dynamic mmap threshold, so every tensor over 128 KiB is then
    mmapped and unmapped on each allocation, and its pages fault in again: on localization at
    1024 px that is twice the system time and about 1 s more per query. This sets the
    thresholds the dynamic rule would reach (mmap above 32 MiB, trim above 64 MiB). A
    user-set ``MALLOC_MMAP_THRESHOLD_`` is left alone. Returns whether it changed anything.
    """
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ or "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):  # not glibc: nothing to restore
        return False
    ok = mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX) == 1
    ok &= mallopt(_M_TRIM_THRESHOLD, 2 * _MMAP_THRESHOLD_MAX) == 1
    logger.debug("malloc thresholds restored: %s", ok)
    return bool(ok)
