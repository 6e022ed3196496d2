"""TaskPool: independent tasks in the caller, in spawned processes, or on a Dask cluster."""

from __future__ import annotations

import os
import time

import pytest

from afmdrift.runs import TaskPool


def _square_where(x: int) -> tuple[int, int]:
    return x * x, os.getpid()


def _slow_square_where(x: int) -> tuple[int, int]:
    # Long enough that the pool hands the first tasks to its process (it
    # queues them at once) while the caller works on one from the back.
    time.sleep(0.3)
    return _square_where(x)


def _fail_on_three(x: int) -> int:
    if x == 3:
        raise ArithmeticError(f"task {x} failed")
    return x


def _die_outside(task: tuple[int, int]) -> int:
    """Kills the process it runs in unless that is the caller (pid ``task[1]``)."""
    x, caller = task
    if os.getpid() != caller:
        os._exit(7)
    time.sleep(0.3)
    return x + 1


def test_processes_and_caller_share_the_work_and_keep_the_order() -> None:
    with TaskPool(2) as pool:
        assert pool.where == "processes"
        pool.wait_started()
        out = pool.map(_slow_square_where, list(range(8)))
    assert [v for v, _ in out] == [x * x for x in range(8)]
    pids = {p for _, p in out}
    assert len(pids) == 2  # a spawned process and the caller
    assert os.getpid() in pids


def _slow_start() -> None:
    time.sleep(4.0)


def test_tasks_wait_for_no_process_that_is_still_starting() -> None:
    """A process still starting (importing, warming up) takes no task: the
    caller does them, so a short map is never slower than without the pool."""
    with TaskPool(2, warm=_slow_start) as pool:
        out = pool.map(_square_where, list(range(6)))
    assert [v for v, _ in out] == [x * x for x in range(6)]
    assert {p for _, p in out} == {os.getpid()}


def test_one_worker_runs_in_the_caller() -> None:
    with TaskPool(1) as pool:
        out = pool.map(_square_where, [1, 2, 3])
    assert pool.where == "serial"
    assert {p for _, p in out} == {os.getpid()}


def test_a_task_that_raises_raises_in_the_caller() -> None:
    with TaskPool(2) as pool, pytest.raises(ArithmeticError, match="task 3 failed"):
        pool.map(_fail_on_three, list(range(6)))


def test_a_dead_worker_process_loses_no_task(caplog: pytest.LogCaptureFixture) -> None:
    me = os.getpid()
    with TaskPool(2) as pool:
        pool.wait_started()  # else the caller may do every task before the process is up
        out = pool.map(_die_outside, [(k, me) for k in range(5)])
    assert out == [1, 2, 3, 4, 5]
    assert pool.where == "serial"
    assert "worker processes stopped" in caplog.text


def test_bad_worker_count_is_refused() -> None:
    with pytest.raises(ValueError, match="workers must be >= 1, got 0"):
        TaskPool(0)


def _pool_in_a_dask_task(n: int) -> tuple[str, list[tuple[int, int]]]:
    with TaskPool(1) as pool:
        return pool.where, pool.map(_square_where, list(range(n)))


def test_inside_a_dask_worker_the_cluster_runs_the_tasks() -> None:
    from distributed import Client, LocalCluster

    with (
        LocalCluster(
            n_workers=1, threads_per_worker=2, processes=False, dashboard_address=":0"
        ) as cluster,
        Client(cluster) as client,
    ):
        where, out = client.submit(_pool_in_a_dask_task, 4).result(timeout=60)
    assert where == "dask"
    assert [v for v, _ in out] == [0, 1, 4, 9]
