"""Executors of a plan's tasks: in this process, or on a Dask distributed cluster.

One place builds Dask clients (a local cluster of worker processes, or an existing
scheduler), annotates tasks with the resources their device needs, gives them keys unique to
the run and retries them when a worker dies. Plans hand over a function and its argument
tuples; nothing here knows about maps or queries.
"""

import contextlib
import logging
import uuid
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Optional, Sequence

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
        is_file = scheduler.endswith(".json") and Path(scheduler).is_file()
        with (Client(scheduler_file=scheduler, timeout=60) if is_file else Client(scheduler)) as client:
            check_resources(client, resources)
            yield client
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


def run_plan(plan, run_sync: Callable, run_dask: Callable, *, sync: bool, scheduler: Optional[str] = None,
             workers: int = 2, device: str = "cpu"):
    """``run_sync(plan, progress=True)``, or ``run_dask(plan, client, progress=True)`` on a client of
    ``scheduler`` (or of a local cluster of ``workers``): what the commands do with a plan."""
    if not scheduler:  # the work runs on this machine (a cluster of yours may have devices that this one has not)
        check_device(device, "; use --device cpu, or run on a cluster whose workers have the GPU (--scheduler)")
    if sync:
        return run_sync(plan, progress=True)
    with dask_client(scheduler, workers, device) as client:
        logger.info("Dask dashboard: %s", client.dashboard_link)
        return run_dask(plan, client, progress=True)


def check_device(device: str, fix: str = "") -> None:
    """Refuse a torch device that this machine does not have (a CUDA device on a CPU build, or past
    the last GPU), with ``fix`` appended: the work would fail one task at a time on torch's assertion."""
    import torch
    dev = torch.device(device)
    if dev.type == "cuda":
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
    out = []
    for args in calls:
        out.append(fn(*args))
        if on_done:
            on_done(out[-1])
    return out


def run_dask(client, fn: Callable, calls: Sequence[tuple], name: str, device: str = "cpu",
             on_done: Optional[Callable] = None) -> List:
    """Submit ``fn(*args)`` per argument tuple to ``client`` (retried if a worker dies) and gather
    the results in order. Keys are unique per run: a key seen before would return its old result."""
    from distributed import as_completed
    resources = task_resources(device)
    check_resources(client, resources)
    run = uuid.uuid4().hex[:8]
    futures = [client.submit(fn, *args, key=f"{name}-{k}-{run}", pure=False, retries=RETRIES,
                             resources=resources) for k, args in enumerate(calls)]
    if on_done:
        for future in as_completed(futures):
            on_done(future.result())
    return client.gather(futures, errors="raise")
