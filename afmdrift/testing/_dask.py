"""A Dask cluster on loopback made of real processes, for tests and benchmarks
of ``afmdrift batch --scheduler``: a ``dask scheduler`` and ``n`` ``dask
worker`` processes (one thread each) started from this interpreter."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import TracebackType

__all__ = ["LoopbackDaskCluster"]


class LoopbackDaskCluster:
    """``with LoopbackDaskCluster(2) as cluster:`` gives ``cluster.address``
    (``tcp://127.0.0.1:PORT``) once every worker has joined; the processes are
    terminated on exit. ``worker_pids`` are the workers' (nanny) processes,
    ``scheduler_pid`` the scheduler's.
    ``env`` is added to the environment of the scheduler and of every worker
    (Dask settings as ``DASK_...`` variables)."""

    def __init__(
        self,
        n_workers: int,
        *,
        timeout_s: float = 120.0,
        env: dict[str, str] | None = None,
    ) -> None:
        if n_workers < 1:
            raise ValueError(f"n_workers must be >= 1, got {n_workers}")
        self.n_workers = n_workers
        self.env = dict(env or {})
        self.timeout_s = timeout_s
        self.address = ""
        self._procs: list[subprocess.Popen[bytes]] = []
        self._tmp = tempfile.TemporaryDirectory(prefix="afmdrift-dask-")

    @property
    def worker_pids(self) -> list[int]:
        return [p.pid for p in self._procs[1:]]

    @property
    def scheduler_pid(self) -> int:
        return self._procs[0].pid

    def __enter__(self) -> LoopbackDaskCluster:
        try:
            self._start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _spawn(self, module: str, *args: str) -> None:
        env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False", **self.env}
        self._procs.append(
            subprocess.Popen(
                [sys.executable, "-m", module, *args, "--no-dashboard"],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                env=env,
                cwd=self._tmp.name,
            )
        )

    def _start(self) -> None:
        from distributed import Client

        file = Path(self._tmp.name) / "scheduler.json"
        self._spawn("distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
                    "--scheduler-file", str(file))  # fmt: skip
        deadline = time.monotonic() + self.timeout_s
        while not (file.is_file() and file.stat().st_size):
            if time.monotonic() > deadline or self._procs[0].poll() is not None:
                raise RuntimeError("the dask scheduler did not start")
            time.sleep(0.1)
        self.address = str(json.loads(file.read_text())["address"])
        for _ in range(self.n_workers):
            self._spawn("distributed.cli.dask_worker", self.address, "--host", "127.0.0.1",
                        "--nworkers", "1", "--nthreads", "1")  # fmt: skip
        with Client(self.address, timeout="30s") as client:
            client.wait_for_workers(self.n_workers, timeout=self.timeout_s)

    def close(self) -> None:
        for p in reversed(self._procs):
            p.terminate()
        for p in self._procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self._procs.clear()
        self._tmp.cleanup()
