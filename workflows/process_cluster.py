"""A Dask cluster of real processes, started with the ``dask`` command: a scheduler on 127.0.0.1
and worker processes without nannies (a killed worker stays dead until another is added). The
tests that claim distribution and the scale benchmarks run on it; ``pixloc`` itself uses a
``LocalCluster`` or a scheduler the user gives (workflows/executor.py)."""

import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Dict, Iterable, Optional

from pipeline.runtime import subprocess_environment

ROOT = Path(__file__).resolve().parents[1]
DASK = Path(sys.executable).parent / "dask"


def wait_for(condition: Callable[[], bool], timeout: float = 120.0, every: float = 0.05) -> None:
    """Poll ``condition`` until it holds; TimeoutError after ``timeout`` seconds."""
    end = time.time() + timeout
    while not condition():
        if time.time() > end:
            raise TimeoutError(f"condition not reached in {timeout:g} s")
        time.sleep(every)


class ProcessCluster:
    """A scheduler (its file in ``work``/scheduler.json) and one worker process per name, one thread
    each, every library held to one thread (torch tasks set their own); the workers run in ``cwd``
    (default: this process's folder) with this process's environment."""

    def __init__(self, work: Path, names: Iterable[str] = ("w0", "w1"), timeout: float = 120.0,
                 cwd: Optional[Path] = None):
        if not DASK.exists():
            raise FileNotFoundError(f"the dask command is not installed next to this Python ({DASK})")
        self.sched = Path(work) / "scheduler.json"
        self.sched.unlink(missing_ok=True)
        self.env = subprocess_environment(OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
        self.cwd = cwd
        self.procs: Dict[str, subprocess.Popen] = {"scheduler": subprocess.Popen(
            [str(DASK), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file",
             str(self.sched)], env=self.env, stderr=subprocess.DEVNULL)}
        names = list(names)
        try:
            wait_for(self.sched.exists, 60)
            for name in names:
                self.add_worker(name)
            self.wait(len(names), timeout)
        except BaseException:
            self.close()
            raise

    def add_worker(self, name: str) -> None:
        self.procs[name] = subprocess.Popen(
            [str(DASK), "worker", "--scheduler-file", str(self.sched), "--nthreads", "1", "--no-nanny",
             "--no-dashboard", "--name", name, "--host", "127.0.0.1", "--memory-limit", "0"],
            env=self.env, cwd=self.cwd, stderr=subprocess.DEVNULL)

    def client(self, timeout: float = 60.0):
        from distributed import Client
        return Client(scheduler_file=str(self.sched), timeout=timeout)

    def wait(self, n: int, timeout: float = 120.0) -> None:
        """Until ``n`` workers are connected."""
        with self.client() as client:
            client.wait_for_workers(n, timeout=timeout)

    def kill(self, name: str) -> None:
        """SIGKILL one process (a worker's name, or "scheduler")."""
        self.procs[name].send_signal(signal.SIGKILL)
        self.procs[name].wait()

    def close(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGKILL)
                p.wait()
