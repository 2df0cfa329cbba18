"""Progress of a long stage, counted in the items a user cares about (queries, images).

On a terminal: a tqdm bar with rate and ETA. Otherwise (a log file, CI, a batch system):
one line when the stage starts, a one-line status at most every ``every`` seconds, and one
line when it ends, instead of a flood of carriage-return bars.
"""

import sys
import threading
import time
from contextlib import closing, contextmanager
from typing import Callable, Iterator, Optional, TextIO


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


class Progress:
    """``with Progress(total, "localize", "query") as p: ... p.update(n)``."""

    def __init__(self, total: int, desc: str, unit: str, plural: Optional[str] = None, stream: Optional[TextIO] = None,
                 every: float = 30.0, terminal: Optional[bool] = None):
        self.total, self.desc, self.unit, self.every = total, desc, unit, every
        self.units = plural or unit + "s"
        self.stream = stream or sys.stderr
        self.terminal = self.stream.isatty() if terminal is None else terminal
        self.done = 0
        self.t0 = self.last = time.perf_counter()
        self.bar = None

    def __enter__(self) -> "Progress":
        if self.terminal:
            from tqdm import tqdm
            self.bar = tqdm(total=self.total, desc=self.desc, unit=self.unit, file=self.stream, smoothing=0.1)
        else:
            self._line(f"{self.desc}: {self.total} {self.unit if self.total == 1 else self.units} to do")
        return self

    def update(self, n: int = 1) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
            return
        now = time.perf_counter()
        if now - self.last >= self.every and self.done < self.total:
            self.last = now
            self._line(self.status())

    def status(self) -> str:
        elapsed = time.perf_counter() - self.t0
        rate = self.done / elapsed if elapsed > 0 else 0.0
        eta = f", ETA {_duration((self.total - self.done) / rate)}" if rate > 0 and self.done < self.total else ""
        return (f"{self.desc}: {self.done}/{self.total} {self.units} ({100 * self.done / max(self.total, 1):.0f} %), "
                f"{rate:.2f} {self.units}/s, elapsed {_duration(elapsed)}{eta}")

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()
        else:
            self._line(self.status() if exc[0] is None else f"{self.desc}: stopped at {self.done}/{self.total}")

    def _line(self, text: str) -> None:
        print(text, file=self.stream, flush=True)


class Silent:
    """What a stage counts into when nobody watches (the default of the library functions that
    take a ``progress`` factory, e.g. ``run_sfm``): ``Silent(total, desc, unit)`` like ``Progress``."""

    def __init__(self, total: int, desc: str, unit: str, plural: Optional[str] = None):
        self.total, self.done = total, 0

    def __enter__(self) -> "Silent":
        return self

    def update(self, n: int = 1) -> None:
        self.done += n

    def __exit__(self, *exc) -> None:
        pass


@contextmanager
def watching(count: Callable[[], int], counter, every: float = 0.5) -> Iterator[None]:
    """Advance ``counter`` to ``count()`` every ``every`` seconds while the block runs, and to its
    total when it ends: the progress of a call that reports none (pycolmap's feature extraction
    and matching release the GIL, so a thread can read their database). A ``count`` that fails
    (the database busy) is read again next time."""
    stop = threading.Event()

    def advance(n: int) -> None:
        n = min(n, counter.total)
        if n > counter.done:
            counter.update(n - counter.done)

    def poll() -> None:
        while not stop.wait(every):
            try:
                advance(count())
            except Exception:  # noqa: BLE001 - a busy or half-written database: try again
                pass

    thread = threading.Thread(target=poll, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
    advance(counter.total)


def database_rows(database, table: str) -> Callable[[], int]:
    """A count of the rows of ``table`` in the SQLite file ``database``, read without taking a lock
    (``immutable``): a reader's shared lock would make COLMAP's next commit fail, and COLMAP aborts
    the process on a failed SQLite call. A torn read raises and is retried by ``watching``."""
    import sqlite3

    def count() -> int:
        with closing(sqlite3.connect(f"file:{database}?mode=ro&immutable=1", uri=True)) as db:
            return int(db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
    return count


def count(n: int, noun: str) -> str:
    """'1 query', '2 queries', '3 finished shards'."""
    if n == 1:
        return f"1 {noun}"
    return f"{n} {noun[:-1] + 'ies' if noun.endswith('y') and noun[-2:-1] not in 'aeiou' else noun + 's'}"
