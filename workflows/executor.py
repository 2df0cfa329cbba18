"""Executors of a plan's tasks: in this process, or on a Dask distributed cluster.

One place builds Dask clients (a local cluster of worker processes, or an existing
scheduler), annotates tasks with the resources their device needs, gives them keys unique to
the run and retries them when a worker dies. Plans hand over a function and its argument
tuples; nothing here knows about maps or queries.
"""

import contextlib
import json
import logging
import uuid
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Optional, Sequence

from pipeline.runtime import InSettings, current

logger = logging.getLogger(__name__)
RETRIES = 3  # a task whose worker dies is rerun elsewhere (tasks are idempotent)


def task_resources(device: str) -> Optional[Dict[str, float]]:
    """Dask resources a task on ``device`` asks for: one ``GPU`` slot on CUDA devices."""
    return {"GPU": 1} if str(device).startswith("cuda") else None


@contextlib.contextmanager
def dask_client(scheduler: Optional[str] = None, workers: int = 2, device: str = "cpu",
                dashboard: bool = True) -> Iterator:
    """A client of ``scheduler`` (an address, or a scheduler file that ``dask scheduler
    --scheduler-file`` wrote), or of a local cluster of ``workers`` processes (one thread each)
    whose workers declare the resources that tasks on ``device`` ask for (a local cluster that
    did not would leave GPU tasks waiting for ever)."""
    from distributed import Client, LocalCluster
    resources = task_resources(device)
    if scheduler:
        address = scheduler_address(scheduler)
        with _quiet_lost_scheduler(), _connected(Client, address, scheduler) as client:  # quiet until closed
            check_resources(client, resources)
            try:
                yield client
            except _lost_scheduler_errors() as e:
                for noisy in ("distributed", "tornado", "asyncio"):  # its comm errors, said once below
                    logging.getLogger(noisy).setLevel(logging.CRITICAL)
                raise SchedulerError(f"--scheduler {scheduler}: the Dask scheduler at {address} went away during "
                                     f"the run ({type(e).__name__}); finished work is kept: run the same command "
                                     "again (with a scheduler) to resume") from None
        return
    if workers < 1:  # a cluster without workers would wait for ever
        raise ValueError(f"--workers must be at least 1, not {workers} (--sync runs in this process).")
    nanny = logging.getLogger("distributed.nanny")
    level = nanny.level
    try:
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, resources=resources,
                          dashboard_address=":0" if dashboard else None) as cluster, Client(cluster) as client:
            client.register_plugin(_interrupt_plugin(), name="pixloc-interrupt")
            try:
                yield client
            except KeyboardInterrupt:
                # Ctrl-C: the cluster is torn down with tasks in flight; its comm errors are not
                # the user's concern (finished shards are on disk: a rerun resumes)
                for noisy in ("distributed", "tornado", "asyncio"):
                    logging.getLogger(noisy).setLevel(logging.CRITICAL)
                raise
            finally:
                # closing: a worker still releasing torch is killed after the timeout, and the nanny's
                # "Worker process still alive ... killing" is noise once every task has finished
                nanny.setLevel(logging.ERROR)
    finally:
        nanny.setLevel(level)


SCHEDULER_TIMEOUT_S = 30.0  # to connect to a --scheduler (distributed's connect timeout): docs/cluster.md
WAIT_NOTE_S = 5.0  # a connection still waiting after this long is said


class SchedulerError(ValueError):
    """A --scheduler that cannot be used, or that went away during a run: said in one line."""


def _lost_scheduler_errors() -> tuple:
    import asyncio
    from concurrent.futures import CancelledError as FutureCancelled

    from distributed.comm.core import CommClosedError
    from distributed.client import FutureCancelledError
    return (CommClosedError, asyncio.CancelledError, FutureCancelled, FutureCancelledError)


@contextlib.contextmanager
def _connected(Client, address: str, scheduler: str):
    """A client of the scheduler at ``address``, connected within ``SCHEDULER_TIMEOUT_S``: distributed's
    own timeout bounds the TCP connect, not an endpoint that accepts and never answers its handshake,
    so the connection is made in a thread that is waited for that long (and left behind after)."""
    import threading

    box: Dict = {}

    def connect():
        try:
            box["client"] = Client(address, timeout=SCHEDULER_TIMEOUT_S)
        except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
            box["error"] = e
    thread = threading.Thread(target=connect, name="pixloc-scheduler-connect", daemon=True)
    thread.start()
    thread.join(WAIT_NOTE_S)
    if thread.is_alive():  # said while waiting, not only when the wait ends
        logger.warning("Still waiting for the Dask scheduler at %s after %.0f s (up to %.0f s)", address, WAIT_NOTE_S,
                       SCHEDULER_TIMEOUT_S)
        thread.join(SCHEDULER_TIMEOUT_S + 5 - WAIT_NOTE_S)
    if "client" not in box:
        e = box.get("error")
        why = f"{type(e).__name__}: {str(e).splitlines()[0][:160]}" if e else "no answer to distributed's handshake"
        raise SchedulerError(f"--scheduler {scheduler}: no Dask scheduler answered at {address} within "
                             f"{SCHEDULER_TIMEOUT_S:g} s ({why})")
    with box["client"] as client:
        yield client


@contextlib.contextmanager
def _quiet_lost_scheduler():
    """While a --scheduler client runs, distributed's own reports of a lost scheduler (its failed
    reconnection, with the tracebacks of the comms it closes) are left out: the run says it once
    (``SchedulerError``). Its other messages pass."""
    lost = _lost_scheduler_errors()

    def keep(record: logging.LogRecord) -> bool:
        if record.exc_info and record.exc_info[0] is not None and issubclass(record.exc_info[0], lost):
            return False
        return not record.getMessage().startswith(("Failed to reconnect", "Lost connection to scheduler"))
    loggers = [logging.getLogger(name) for name in ("distributed.client", "distributed.utils", "distributed.core")]
    for logger_ in loggers:
        logger_.addFilter(keep)
    try:
        yield
    finally:
        for logger_ in loggers:
            logger_.removeFilter(keep)


def scheduler_address(scheduler: str) -> str:
    """The address of ``--scheduler``: as given, or read from the scheduler file that ``dask scheduler
    --scheduler-file`` wrote (a JSON object with an ``address``), checked here: distributed fails
    on a damaged one with a bare AssertionError."""
    path = Path(scheduler)
    if "://" in scheduler and not path.is_file():
        return scheduler
    if not path.exists() and not scheduler.endswith(".json"):
        return scheduler  # host:port
    from pipeline.textfiles import read_json
    info = read_json(path, "Dask scheduler file (--scheduler)")
    address = info.get("address")
    if not isinstance(address, str) or "://" not in address:
        raise SchedulerError(f"{path}: Dask scheduler file (--scheduler) has no scheduler address (a string "
                             f"like tcp://host:8786 under 'address'), got {json.dumps(address)[:60]}: is the "
                             "scheduler running, and is this the file it wrote?")
    return address


def _interrupt_plugin():
    """A worker plugin of the local cluster: Ctrl-C in a terminal goes to every process of its group,
    and each worker process printed a KeyboardInterrupt traceback, then a warning per cancelled task
    as the client tore the cluster down. The workers now leave Ctrl-C to the client (which stops the
    run, said once), and drop those warnings (a rerun resumes the cancelled shards); SIGTERM ends a
    worker without the stack dump of glog's failure handler (installed with pycolmap)."""
    from distributed import WorkerPlugin

    class LeaveInterruptToClient(WorkerPlugin):
        def setup(self, worker) -> None:
            import signal
            import threading
            if threading.current_thread() is threading.main_thread():  # a worker process runs its loop there
                signal.signal(signal.SIGINT, signal.SIG_IGN)
                signal.signal(signal.SIGTERM, signal.SIG_DFL)  # stopped by its nanny: not glog's stack dump
            logging.getLogger("distributed.worker.state_machine").addFilter(_not_cancelled)

        def teardown(self, worker) -> None:  # closing: the scheduler may go first, mid-heartbeat
            logging.getLogger("distributed").setLevel(logging.CRITICAL)
    return LeaveInterruptToClient()


def _not_cancelled(record: logging.LogRecord) -> bool:
    return "ended with CancelledError" not in record.getMessage()


class Session:
    """Where one command's tasks run: in this process (``sync``), or on a Dask client of
    ``scheduler`` (or of a local cluster of ``workers``) started on first use and closed with the
    session, so that every stage of a command (a build's SIFT, matching and features) shares one
    cluster, and a command with nothing to do starts none."""

    def __init__(self, *, sync: bool, scheduler: Optional[str] = None, workers: int = 2, device: str = "cpu"):
        # on this machine the device must be here; a cluster of yours may have devices that this one has not
        check_device(device, "; use --device cpu, or run on a cluster whose workers have the GPU (--scheduler)",
                     here=not scheduler)
        self.sync, self.scheduler, self.workers, self.device = sync, scheduler, workers, device
        self._stack = contextlib.ExitStack()
        self._client = None

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc):
        return self._stack.__exit__(*exc)

    @property
    def client(self):
        """The Dask client (None when ``sync``), started on first use."""
        if self.sync:
            return None
        if self._client is None:
            self._client = self._stack.enter_context(dask_client(self.scheduler, self.workers, self.device))
            logger.info("Dask dashboard: %s", self._client.dashboard_link)
        return self._client

    def run(self, fn: Callable, calls: Sequence[tuple], name: str, on_done: Optional[Callable] = None) -> List:
        """``fn(*args)`` per argument tuple (``run_sync`` or ``run_dask``); CPU tasks (the device's
        resources are for the plan's own tasks)."""
        if self.sync or not calls:
            return run_sync(fn, calls, on_done)
        return run_dask(self.client, fn, calls, name, "cpu", on_done)

    def run_plan(self, plan, run_sync: Callable, run_dask: Callable):
        """``run_sync(plan, progress=True)``, or ``run_dask(plan, client, progress=True)``."""
        if self.sync:
            return run_sync(plan, progress=True)
        return run_dask(plan, self.client, progress=True)


def run_plan(plan, run_sync: Callable, run_dask: Callable, *, sync: bool, scheduler: Optional[str] = None,
             workers: int = 2, device: str = "cpu"):
    """``run_sync(plan, progress=True)``, or ``run_dask(plan, client, progress=True)`` on a client of
    ``scheduler`` (or of a local cluster of ``workers``): what the commands do with a plan."""
    with Session(sync=sync, scheduler=scheduler, workers=workers, device=device) as session:
        return session.run_plan(plan, run_sync, run_dask)


def check_device(device: str, fix: str = "", here: bool = True) -> None:
    """Refuse a device name that is none of cpu, cuda, cuda:N, and (``here``) a torch device that this
    machine does not have (a CUDA device on a CPU build, or past the last GPU), with ``fix`` appended:
    the work would fail one task at a time on torch's assertion."""
    import torch
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        dev = None
    if dev is None or dev.type not in ("cpu", "cuda"):
        raise ValueError(f"--device {device}: not a device this program runs on (cpu, cuda, or cuda:N).")
    if dev.type == "cuda" and here:
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (dev.index or 0) >= count:
            none = "" if count else " (no CUDA device is available to torch here: a CPU build, or no GPU)"
            raise ValueError(f"--device {device}: this machine has {count} CUDA device(s){none}{fix}.")


def check_resources(client, resources: Optional[Dict[str, float]]) -> None:
    """Refuse to submit tasks that no worker of the cluster could ever run."""
    if not resources:
        return
    info = client.scheduler_info()["workers"]
    able = [w for w in info.values() if all(w.get("resources", {}).get(k, 0) >= v for k, v in resources.items())]
    if not able:
        raise ValueError(f"No worker of the Dask cluster declares the resources {resources} that the tasks need: "
                         "start the workers with e.g. 'dask worker ADDRESS --resources GPU=1'.")


def run_sync(fn: Callable, calls: Sequence[tuple], on_done: Optional[Callable] = None) -> List:
    """Run ``fn(*args)`` for each argument tuple, in order, in this process."""
    from pipeline.mapping.structure import in_process
    return in_process(fn, calls, "in this process", on_done)


def run_dask(client, fn: Callable, calls: Sequence[tuple], name: str, device: str = "cpu",
             on_done: Optional[Callable] = None) -> List:
    """Submit ``fn(*args)`` per argument tuple to ``client`` (retried if a worker dies) and gather
    the results in order. Keys are unique per run: a key seen before would return its old result."""
    from distributed import as_completed
    resources = task_resources(device)
    check_resources(client, resources)
    run = uuid.uuid4().hex[:8]
    task = InSettings(fn, current())  # the run's settings reach every worker, an external scheduler's too
    futures = [client.submit(task, *args, key=f"{name}-{k}-{run}", pure=False, retries=RETRIES,
                             resources=resources) for k, args in enumerate(calls)]
    if on_done:
        for future in as_completed(futures):
            on_done(future.result())
    return client.gather(futures, errors="raise")
