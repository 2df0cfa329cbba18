"""The executors: one place that builds Dask clients, annotates resources and keys tasks."""

import operator

import pytest

from workflows import executor


def test_gpu_annotated_tasks_run_on_the_local_cluster():
    """Before: --device cuda on the default local cluster hung (tasks asked for a GPU resource that
    no worker declared). A local cluster for a CUDA device declares it; the tasks here are plain."""
    assert executor.task_resources("cuda:0") == {"GPU": 1} and executor.task_resources("cpu") is None
    with executor.dask_client(workers=1, device="cuda", dashboard=False) as client:
        assert executor.run_dask(client, operator.neg, [(1,), (2,)], "neg", device="cuda") == [-1, -2]
        assert executor.run_dask(client, operator.neg, [(3,)], "neg", device="cuda") == [-3]  # keys unique per run


def test_a_cluster_that_cannot_run_gpu_tasks_is_refused_not_waited_on():
    with executor.dask_client(workers=1, device="cpu", dashboard=False) as client:
        with pytest.raises(ValueError, match="declares the resources"):
            executor.run_dask(client, operator.neg, [(1,)], "neg", device="cuda")
        done = []
        assert executor.run_dask(client, operator.neg, [(1,), (2,)], "neg", on_done=done.append) == [-1, -2]
        assert sorted(done) == [-2, -1]


def test_sync_executor_runs_in_order():
    assert executor.run_sync(operator.add, [(1, 2), (3, 4)]) == [3, 7]
