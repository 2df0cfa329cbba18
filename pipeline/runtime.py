"""Process-level settings of pipeline tasks."""

from contextlib import contextmanager
from typing import Iterator

import torch


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
