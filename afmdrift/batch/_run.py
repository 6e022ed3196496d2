"""An archive of recordings through Dask.distributed: a LocalCluster on this
machine by default, or an existing cluster (``dask scheduler`` with ``dask
worker``s, dask-jobqueue on SLURM, Kubernetes) by its scheduler address.

The client only names the recordings: each worker reads its recording itself
and writes its output under ``OUT/<stem>/``. As each recording finishes, the
client rewrites ``OUT/summary.csv``; a recording already done with the same
input and configuration (its ``result.json``) is not run again.
"""

from __future__ import annotations

import copy
import glob
import logging
import os
import sys
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, TextIO

from afmdrift._cores import available_cores
from afmdrift.batch._jobs import Job, Result, Task, fingerprint, load_result, run_job, stems
from afmdrift.batch._summary import plot_archive, write_summary
from afmdrift.config import AfmdriftConfig
from afmdrift.errors import ConfigError, InputError

__all__ = [
    "DASK_SETTINGS",
    "SCHEDULER_ENV",
    "BatchReport",
    "Recording",
    "dask_environ",
    "expand_inputs",
    "run_batch",
]

log = logging.getLogger(__name__)

#: Environment variable naming the scheduler when ``--scheduler`` is not given.
SCHEDULER_ENV = "AFMDRIFT_SCHEDULER"

#: Dask settings for tasks that take seconds (one recording each), where Dask's
#: defaults serve tasks of milliseconds. The command's own LocalCluster runs
#: with them (scheduler and workers); for a cluster of your own, start ``dask
#: scheduler`` and ``dask worker`` with :func:`dask_environ` (the README lists
#: them). By default each worker's statistical profiler samples its task
#: thread's stack every 10 ms, every Dask server checks its event loop every
#: 20 ms and the memory monitor reads the worker's RSS every 100 ms: on two
#: workers on two cores that is CPU taken from the tasks (the figures are in
#: benchmarks/RESULTS.md). What these settings give up: the dashboard's profile
#: page (empty), the warning of a blocked event loop (up to 0.5 s later), a
#: memory limit's check (every 0.5 s).
DASK_SETTINGS: dict[str, object] = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "500ms",
    "distributed.worker.memory.monitor-interval": "500ms",
}


def dask_environ() -> dict[str, str]:
    """:data:`DASK_SETTINGS` as the environment variables Dask reads at
    start-up: ``distributed.admin.tick.interval`` becomes
    ``DASK_DISTRIBUTED__ADMIN__TICK__INTERVAL=500ms``."""
    out = {}
    for key, value in DASK_SETTINGS.items():
        name = "DASK_" + "__".join(part.replace("-", "_").upper() for part in key.split("."))
        out[name] = str(value)
    return out


@dataclass(frozen=True, slots=True)
class BatchReport:
    """What :func:`run_batch` did."""

    results: list[Result]
    skipped: int
    summary: Path

    @property
    def failed(self) -> int:
        return sum(r.status == "failed" for r in self.results)


class Recording(NamedTuple):
    """One recording of the inputs: ``name`` as the user named it (a file, a
    session directory, or the folder or glob of a series) and, for a series of
    single-image files, those files (read as ``afmdrift import`` reads them)."""

    name: str
    files: tuple[str, ...] = ()


def expand_inputs(inputs: Sequence[str]) -> list[Recording]:
    """Recordings named by ``inputs``: files and session directories as given,
    globs expanded (sorted), and the image files directly inside a directory that
    is not a session. The files of one folder or glob that each hold one image
    (a NanoScope ``.000``–``.999`` series, 2-D ``.npy`` files) are one series:
    one recording, named by the folder or glob. A name that matches nothing is
    kept: it becomes a failed row naming it.

    Raises
    ------
    InputError
        A glob matches nothing, or a folder holds no image file (a usage error).
    """
    from afmdrift.io import holds_one_image, is_image_file

    out: list[Recording] = []
    for spec in inputs:
        if glob.has_magic(spec):
            matches = sorted(glob.glob(spec, recursive=True))
            if not matches:
                raise InputError(f"{spec}: matches no file")
        elif Path(spec).is_dir() and not (Path(spec) / "session.json").is_file():
            matches = sorted(str(p) for p in Path(spec).iterdir() if is_image_file(p))
            if not matches:
                raise InputError(f"{spec}: neither a session directory nor a folder of images")
        else:
            out.append(Recording(spec))
            continue
        series = tuple(m for m in matches if is_image_file(m) and holds_one_image(m))
        alone = set(matches).difference(series)
        out.extend(Recording(m) for m in matches if m in alone)
        if len(series) == 1:
            out.append(Recording(series[0]))
        elif series:
            out.append(Recording(spec, series))
    seen: set[tuple[str, ...]] = set()
    unique = []
    for rec in out:
        key = tuple(os.path.abspath(f) for f in (rec.files or (rec.name,)))
        if key not in seen:
            seen.add(key)
            unique.append(rec)
    return unique


def run_batch(
    inputs: Sequence[str],
    out: Path,
    *,
    task: Task,
    config: AfmdriftConfig,
    workers: int | None = None,
    scheduler: str | None = None,
    pixel_size_nm: tuple[float, float] | None = None,
    channel: str = "Height",
    height_unit: str | None = None,
    progress: TextIO | None = None,
    override_pixel_size: bool = False,
    prior_px: tuple[float, float] | None = None,
) -> BatchReport:
    """Run ``task`` on every recording of ``inputs``; see the module docstring.

    ``workers``: LocalCluster processes (default: one per core) when no
    ``scheduler`` address is given (nor ``$AFMDRIFT_SCHEDULER``). Each worker
    runs one recording at a time with one registration thread. ``progress``:
    a terminal to show recordings and frames done, with the rate.
    ``pixel_size_nm`` serves the files without a calibration, and replaces
    a header's only with ``override_pixel_size``; ``prior_px`` is the
    expected drift of each recording's first frame after the first.
    """
    found = expand_inputs(inputs)
    recordings = [rec.name for rec in found]
    out.mkdir(parents=True, exist_ok=True)
    # the workers report frames done to this run's own topic, for the terminal
    topic = f"afmdrift-batch-progress-{uuid.uuid4().hex[:12]}" if progress is not None else ""
    # one registration thread per worker: the workers are the parallelism
    registration = config.registration.model_copy(update={"threads": 1})
    cfg = config.model_copy(update={"registration": registration}).model_dump(mode="json")
    jobs = []
    for rec, stem in zip(found, stems(recordings), strict=True):
        job = Job(
            recording=rec.name,
            path=os.path.abspath(rec.name),
            files=tuple(os.path.abspath(f) for f in rec.files),
            out=str(out / stem),
            task=task,
            config=cfg,
            pixel_size_nm=pixel_size_nm,
            channel=channel,
            height_unit=height_unit,
            progress_topic=topic,
            override_pixel_size=override_pixel_size,
            prior_px=prior_px,
        )
        jobs.append(Job(**{**_fields(job), "key": fingerprint(job)}))
    rows: list[Result | None] = [load_result(job, job.key) for job in jobs]
    skipped = sum(r is not None for r in rows)
    todo = [k for k, r in enumerate(rows) if r is None]
    summary = out / "summary.csv"
    write_summary(summary, rows, recordings)
    show = _Progress(progress, total=len(jobs), done=skipped)
    if skipped:
        show.line(f"{skipped} of {len(jobs)} recordings already done; skipping them")
    if todo:
        address = scheduler or os.environ.get(SCHEDULER_ENV) or None

        def finished(k: int, result: Result) -> None:
            rows[k] = result
            write_summary(summary, rows, recordings)
            show.advance(result, jobs[k].out)

        _on_cluster([jobs[k] for k in todo], todo, finished, address, workers, show)
    show.close()
    final = [r for r in rows if r is not None]
    try:
        plot_archive(out / "archive.svg", rows, [Path(j.out).name for j in jobs])
    except (OSError, ValueError) as err:
        log.warning("archive picture not written: %s", err)
    return BatchReport(results=final, skipped=skipped, summary=summary)


def _fields(job: Job) -> dict[str, Any]:
    return {f: getattr(job, f) for f in job.__dataclass_fields__}


def _on_cluster(
    jobs: list[Job],
    index: list[int],
    finished: Callable[[int, Result], None],
    address: str | None,
    workers: int | None,
    show: _Progress,
) -> None:
    """Submit ``jobs`` and hand each result to ``finished`` as it comes."""
    from distributed import Client, as_completed

    logging.getLogger("distributed").setLevel(logging.ERROR)
    cluster = None
    try:
        if address is None:
            cluster = _local_cluster(workers)
            client = Client(cluster)
        else:
            client = Client(address, timeout="20s")
    except (OSError, TimeoutError, ValueError) as err:
        target = address or "a local cluster"
        raise ConfigError(f"cannot reach the Dask scheduler {target}: {err}") from None
    try:
        for topic in {job.progress_topic for job in jobs} - {""}:
            client.subscribe_topic(topic, show.event)
        link = getattr(client, "dashboard_link", None)
        if link and (cluster is None or _has_dashboard()):
            show.line(f"Dask dashboard: {link}")
        futures = {
            client.submit(run_job, job, key=f"afmdrift-batch-{job.key[:16]}-{k}", retries=1): k
            for k, job in zip(index, jobs, strict=True)
        }
        for future in as_completed(futures):
            k = futures[future]
            try:
                result = future.result()
            except Exception as err:  # a worker died on it (KilledWorker, lost memory)
                job = jobs[index.index(k)]
                text = " ".join(str(err).split()) or type(err).__name__
                result = Result(
                    recording=job.recording,
                    status="failed",
                    error=f"{job.recording}: {type(err).__name__}: {text}",
                )
            finished(k, result)
    finally:
        client.close()  # and with it the progress subscriptions
        if cluster is not None:
            cluster.close()


def _has_dashboard() -> bool:
    try:
        import bokeh  # noqa: F401
    except ImportError:
        return False
    return True


def _local_cluster(workers: int | None) -> Any:
    """A LocalCluster of ``workers`` processes with :data:`DASK_SETTINGS` (the
    scheduler reads them here, and each nanny passes them to its worker),
    except a setting the user changed from Dask's default, which is kept."""
    import dask
    from distributed import LocalCluster

    n = workers if workers is not None else available_cores()
    if n < 1:
        raise ConfigError(f"--workers must be >= 1, got {n}")
    with dask.config.set(_unless_configured(DASK_SETTINGS)):
        # each nanny's own copy, for a worker it restarts after this block too
        # (it would otherwise share the nested dicts that leaving the block resets)
        nanny_config = {"distributed": copy.deepcopy(dask.config.get("distributed"))}
        return LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            # a free port: Dask's 8787 may be taken, and its warning names no recording
            dashboard_address=":0",
            silence_logs=logging.ERROR,
            config=nanny_config,
        )


def _unless_configured(settings: dict[str, object]) -> dict[str, object]:
    """``settings`` without those the user configured: named in a Dask YAML file
    or a ``DASK_...`` variable (whatever the value), or set in this process to
    a value other than Dask's own default."""
    import dask

    defaults: dict[str, Any] = {}
    for d in dask.config.defaults:
        dask.config.update(defaults, d)
    user = dask.config.collect()  # the YAML files and the environment, no defaults
    return {
        key: value
        for key, value in settings.items()
        if dask.config.get(key, None, config=user) is None
        and dask.config.get(key, None) == dask.config.get(key, None, config=defaults)
    }


class _Progress:
    """Recordings and frames done, with the rate, on one terminal line: the
    frames of the recordings finished, and those the workers report from the
    recordings they are on (:meth:`event`, in the Dask client's thread)."""

    def __init__(self, stream: TextIO | None, *, total: int, done: int) -> None:
        self.stream = stream
        self.total = total
        self.done = done
        self.frames = 0
        self.failed = 0
        self.started = time.monotonic()
        self._lock = threading.Lock()
        self._running: dict[str, int] = {}
        self._finished: set[str] = set()

    def line(self, text: str) -> None:
        print(text, file=self.stream or sys.stderr, flush=True)

    def event(self, event: tuple[float, Any]) -> None:
        """A worker's report (a Dask event ``(time, {"out", "frames"})``): the
        frames done so far in the recording it writes to ``out``. A report that
        arrives after its recording finished is ignored."""
        try:
            _, msg = event
            out, frames = str(msg["out"]), int(msg["frames"])
        except (TypeError, KeyError, ValueError):
            return
        with self._lock:
            if out not in self._finished:
                self._running[out] = frames
                self._draw()

    def advance(self, result: Result, out: str = "") -> None:
        with self._lock:
            self._finished.add(out)
            self._running.pop(out, None)
            self.done += 1
            self.frames += result.frames
            self.failed += result.status == "failed"
            self._draw()

    def _draw(self) -> None:
        if self.stream is None:
            return
        frames = self.frames + sum(self._running.values())
        rate = frames / max(time.monotonic() - self.started, 1e-9)
        self.stream.write(
            f"\r{self.done}/{self.total} recordings ({self.failed} failed), "
            f"{frames} frames, {rate:.1f} frames/s"
        )
        self.stream.flush()

    def close(self) -> None:
        if self.stream is not None and self.done:
            self.stream.write("\n")
            self.stream.flush()
