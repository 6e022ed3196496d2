"""One recording of an archive: what a worker does with it, and how a later run
knows that it is done.

A :class:`Job` names a recording (a stack or movie file, a series of
single-image files, or a session directory), the task and every option that
changes its output. The worker reads the recording itself (frames are never
shipped from the client), runs the task, writes its output under
``OUT/<stem>/`` and, last, ``result.json`` with the job's fingerprint: a later
run with the same input and configuration finds it and skips the recording,
also after the first run was killed.

The tasks (:data:`TASKS`):

``measure``
    ``track.jsonl``: the lines of ``afmdrift measure STACK --json``.
``correct``
    the same, and the drift-corrected frames (``corrected/frames.npy`` and
    ``frames.csv`` as ``afmdrift correct --format npy`` writes them, and
    ``corrected.tif``).
``replay`` (a session directory)
    ``run/``: the run directory ``afmdrift replay SESSION --out run`` writes.
``diagnose`` (a session directory)
    the same ``run/``, kept as ``afmdrift diagnose --run-dir run`` keeps it;
    ``diagnosis.json`` (what ``--json`` prints), ``diagnosis.txt`` (what it
    prints without) and ``report.html`` (``--report``).

Every task goes through :mod:`afmdrift.runs` (and, for ``diagnose``,
:mod:`afmdrift.diagnostics`): a worker never imports the daemon
(:mod:`afmdrift.service`) nor ZeroMQ, which import-linter keeps so.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import re
import shutil
import threading
import time
import traceback
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from afmdrift._version import __version__
from afmdrift.batch._heap import job_heap
from afmdrift.config import AfmdriftConfig
from afmdrift.errors import AfmdriftError, InputError

__all__ = ["TASKS", "Job", "Result", "fingerprint", "load_result", "run_job"]

log = logging.getLogger(__name__)

Task = Literal["measure", "correct", "replay", "diagnose"]
#: What ``afmdrift batch --task`` can do to each recording.
TASKS: tuple[Task, ...] = ("measure", "correct", "replay", "diagnose")
#: The tasks that need a session directory (its channels and events).
SESSION_TASKS: tuple[Task, ...] = ("replay", "diagnose")

RESULT_FILE = "result.json"
#: Statuses of a recording that a later run skips (``failed`` is tried again).
FINISHED = ("done", "no_drift")


@dataclass(frozen=True, slots=True)
class Job:
    """One recording and what to do with it (picklable: it travels to a worker).

    ``recording`` is the input as given, ``path`` its absolute path, ``out``
    the recording's own output directory. ``files``: for a series of
    single-image files (``recording`` their folder or glob), those files,
    absolute, read as ``afmdrift import`` reads them; empty otherwise.
    """

    recording: str
    path: str
    out: str
    task: Task
    config: dict[str, Any]
    pixel_size_nm: tuple[float, float] | None = None
    channel: str = "Height"
    height_unit: str | None = None
    key: str = field(default="")
    #: ``--override-pixel-size``: ``pixel_size_nm`` replaces a header's calibration.
    override_pixel_size: bool = False
    #: ``--prior-px``: the expected drift of the first frame after the first, px.
    prior_px: tuple[float, float] | None = None
    #: The Dask event topic to which a worker reports the frames done so far
    #: (every :data:`PROGRESS_INTERVAL_S`); empty: no reports. Not part of the
    #: fingerprint: it changes no output.
    progress_topic: str = ""
    files: tuple[str, ...] = ()


#: Seconds between two reports of a recording's frames done (``progress_topic``).
PROGRESS_INTERVAL_S = 0.5


@dataclass(slots=True)
class Result:
    """What a job gives the summary (one row of ``summary.csv``)."""

    recording: str
    #: ``done``; ``no_drift``: read and run, but no frame after the first was
    #: measured (the drift columns are empty, ``error`` says why); ``failed``.
    status: Literal["done", "no_drift", "failed"]
    frames: int = 0
    valid_frames: int = 0
    #: Of the valid frames, those whose shift the prior alone picked among
    #: lattice translations (``decided_by: "prior"``).
    prior_decided: int = 0
    drift_x_nm: float = math.nan
    drift_y_nm: float = math.nan
    worker: str = ""
    seconds: float = 0.0
    error: str = ""
    #: Time from the first to the last frame, s (for the archive's picture).
    duration_s: float = math.nan
    fingerprint: str = ""

    def to_json(self) -> dict[str, Any]:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in asdict(self).items()}  # fmt: skip

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> Result:
        known = set(cls.__dataclass_fields__)
        values: dict[str, Any] = {
            k: (math.nan if v is None else v) for k, v in doc.items() if k in known
        }
        return cls(**values)


def fingerprint(job: Job) -> str:
    """What makes a job's output: the input's files (size and modification time),
    the task, the options and the configuration, and afmdrift's version."""
    path = Path(job.path)
    if job.files:
        files = [Path(f) for f in job.files]
    elif path.is_dir():
        files = sorted(p for p in path.rglob("*") if p.is_file())
    else:
        files = [path]
    stats = []
    for p in files:
        try:
            st = p.stat()
        except OSError:
            continue
        stats.append((str(p), st.st_size, st.st_mtime_ns))
    doc = {
        "version": __version__,
        "task": job.task,
        "files": stats,
        "config": job.config,
        "pixel_size_nm": job.pixel_size_nm,
        "channel": job.channel,
        "height_unit": job.height_unit,
        "override_pixel_size": job.override_pixel_size,
        "prior_px": job.prior_px,
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def load_result(job: Job, key: str) -> Result | None:
    """The recorded result of ``job`` if it is done with this fingerprint ``key``."""
    try:
        doc = json.loads((Path(job.out) / RESULT_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if (
        not isinstance(doc, dict)
        or doc.get("fingerprint") != key
        or doc.get("status") not in FINISHED
    ):
        return None
    try:
        return Result.from_json(doc)
    except TypeError:
        return None


def run_job(job: Job) -> Result:
    """Run ``job`` (on a Dask worker or in this process); never raises for a bad
    recording: the failure is the result, with one line naming the file."""
    started = time.perf_counter()
    result = Result(recording=job.recording, status="done", worker=_worker_address())
    try:
        with job_heap(), named_warnings(job.recording):
            _work(job, result)
    except (AfmdriftError, OSError, ValueError, MemoryError) as err:
        result.status = "failed"
        result.error = _one_line(job.recording, err)
    except Exception as err:  # a bug must not stop the archive: it is this row's error
        result.status = "failed"
        where = traceback.extract_tb(err.__traceback__)[-1]
        result.error = _one_line(
            job.recording, f"{type(err).__name__}: {err} (at {where.filename}:{where.lineno})"
        )
    result.seconds = time.perf_counter() - started
    result.fingerprint = job.key
    if result.status in FINISHED:
        _atomic_write(Path(job.out) / RESULT_FILE, json.dumps(result.to_json()) + "\n")
    return result


def _work(job: Job, result: Result) -> None:
    """Read ``job``'s recording, run its task and write its output; the
    counts and last drift into ``result``."""
    out = Path(job.out)
    out.mkdir(parents=True, exist_ok=True)
    _clear_result(out)
    if job.task in SESSION_TASKS and (job.files or not Path(job.path).is_dir()):
        raise InputError(
            f"{job.recording}: --task {job.task} needs a session directory "
            "(format v1, with its channels and events), not a stack, movie or image series"
        )
    session, timed = _read(job)
    config = AfmdriftConfig.model_validate(job.config)
    report = _frame_reporter(job)
    if job.task in SESSION_TASKS:
        _replay(session, config, out / "run", result, report, prior_px=job.prior_px)
        if job.task == "diagnose":
            _diagnose(Path(job.path), config, out)
    else:
        _measure(session, config, timed, out / "track.jsonl", result, report, prior_px=job.prior_px)
    if job.task == "correct":
        _correct(session, config, out, prior_px=job.prior_px)
    mids = session.frame_times.mean(axis=1)
    result.duration_s = float(mids[-1] - mids[0])


# --------------------------------------------------------------------------- steps


def _read(job: Job) -> tuple[Any, bool]:
    """The recording as a session, and whether its frame times are the instrument's."""
    from afmdrift.io import calibrated, load_stack
    from afmdrift.session import SessionError, read_session, stack_session

    path = Path(job.path)
    if path.is_dir() and not job.files:
        return read_session(path, mmap=True), True

    def read(file: Path, pixel_size_nm: tuple[float, float] | None) -> list[Any]:
        return load_stack(
            file,
            pixel_size_nm=pixel_size_nm,
            channel=job.channel,
            height_unit=job.height_unit,
            stream=True,
        )

    def read_calibrated(file: Path) -> list[Any]:
        stack, note = calibrated(
            lambda px: read(file, px), job.pixel_size_nm, override=job.override_pixel_size,
            pixel_of=lambda images: images[0].pixel_size_nm,
        )  # fmt: skip
        if note is not None:
            log.warning("%s: %s", file, note)
        return stack

    # a series of single-image files is one recording, ordered and timed as
    # `afmdrift import` orders and times them (session_from_images)
    images = [im for file in job.files or (job.path,) for im in read_calibrated(Path(file))]
    if len(images) < 2:
        raise SessionError(f"{path}: holds one image; a recording needs two frames or more")
    return stack_session(images)


def _measure(
    session: Any,
    config: AfmdriftConfig,
    timed: bool,
    path: Path,
    result: Result,
    report: Callable[[int], None],
    *,
    prior_px: tuple[float, float] | None,
) -> None:
    """``afmdrift measure STACK --json``'s lines into ``path``; the summary's
    counts and last measured drift into ``result`` (none when no frame was
    measured); ``report`` is given the frames done after each."""
    from afmdrift.runs import track_session

    tmp = path.with_name(path.name + ".tmp")
    result.frames = 1
    refusals: list[str] = []
    with tmp.open("w", encoding="utf-8") as fh:
        for doc in track_session(session, config, timed=timed, prior_px=prior_px):
            fh.write(json.dumps(doc) + "\n")
            result.frames += 1
            if doc.get("valid"):
                result.valid_frames += 1
                result.prior_decided += doc.get("decided_by") == "prior"
                result.drift_x_nm = doc["cumulative_dx_nm"]
                result.drift_y_nm = doc["cumulative_dy_nm"]
            else:
                refusals.append(
                    f"frame {doc['cur_frame']}: {doc.get('reason') or doc.get('error')}"
                )
            report(result.frames)
    os.replace(tmp, path)
    _no_drift(result, refusals)


def _no_drift(result: Result, refusals: list[str]) -> None:
    """A recording none of whose frames was measured: status ``no_drift``,
    no drift, and why (the first refusal) in ``error``."""
    if result.valid_frames == 0:
        result.status = "no_drift"
        result.drift_x_nm = result.drift_y_nm = math.nan
        why = refusals[0] if refusals else "no frame after the first"
        result.error = f"no frame was measured ({why})"


def _correct(
    session: Any, config: AfmdriftConfig, out: Path, *, prior_px: tuple[float, float] | None
) -> None:
    """``afmdrift correct --format npy``'s output, and the same frames as an
    ImageJ TIFF stack (pixel size and frame times) that Fiji and Gwyddion open."""
    import numpy as np
    import tifffile

    from afmdrift.runs import correct_session

    summary = correct_session(
        session, out / "corrected", config=config, output="npy", prior_px=prior_px
    )
    frames = np.load(out / "corrected" / "frames.npy", mmap_mode="r")
    px, py = session.meta.pixel_size_nm
    skipped = set(summary.frames_skipped)
    kept = [k for k in range(len(session)) if k not in skipped]
    starts = session.frame_times[kept, 0] if kept else np.zeros(0)
    interval = float(np.median(np.diff(starts))) if starts.size > 1 else 1.0
    tmp = out / "corrected.tif.tmp"
    tifffile.imwrite(
        tmp,
        np.asarray(frames, dtype=np.float32),
        imagej=True,
        resolution=(1.0 / px, 1.0 / py),
        metadata={
            "axes": "TYX",
            "unit": "nm",
            "finterval": interval,
            "spacing": 1.0,
            "Info": json.dumps({"frame_start_s": [float(t) for t in starts]}),
        },
    )
    os.replace(tmp, out / "corrected.tif")


def _replay(
    session: Any,
    config: AfmdriftConfig,
    run: Path,
    result: Result,
    report: Callable[[int], None],
    *,
    prior_px: tuple[float, float] | None,
) -> None:
    """``afmdrift replay SESSION --out run``; the summary's counts and the
    last measured drift position p (commanded moves removed) into
    ``result`` (none when no frame was measured); ``report`` is given the
    frames done as they are."""
    from afmdrift.runs import RunStore, replay_session

    # A run left by a job killed halfway: replay writes only into an empty directory.
    shutil.rmtree(run, ignore_errors=True)
    summary = replay_session(session, run, config=config, on_frame=report, prior_px=prior_px)
    result.prior_decided = summary.prior_decided
    with RunStore(run) as store:
        records = store.frames()
    result.frames = len(records)
    refusals: list[str] = []
    for r in records[1:]:
        # measured: valid with an increment (a reference has none: its p is 0
        # or carried across from the frames before it, never measured)
        if r.valid and math.isfinite(r.dx_nm):
            result.valid_frames += 1
            result.drift_x_nm, result.drift_y_nm = r.x_nm, r.y_nm
        elif not r.valid:
            refusals.append(f"frame {r.seq}: {r.reason}")
    _no_drift(result, refusals)


def _diagnose(session_dir: Path, config: AfmdriftConfig, out: Path) -> None:
    """What ``afmdrift diagnose SESSION --run-dir run --report report.html``
    writes and prints (``--json`` and without), from the run :func:`_replay`
    wrote into ``out / "run"``."""
    from afmdrift.diagnostics import diagnose, diagnosis_text, load_run, write_report

    data = load_run(out / "run", session_dir=session_dir)
    diagnosis = diagnose(data, config.model.physics)
    doc = diagnosis.to_json()
    _atomic_write(out / "diagnosis.json", json.dumps(doc, indent=2) + "\n")
    _atomic_write(out / "diagnosis.txt", diagnosis_text(doc) + "\n")
    write_report(diagnosis, data, out / "report.html", registration=config.registration)


# --------------------------------------------------------------------------- warnings

#: The recording of the job each thread of this process runs (a Dask worker
#: runs one job per thread); :func:`named_warnings` keeps it.
_running: dict[int, str] = {}
_running_lock = threading.Lock()
_warning_handler: logging.Handler | None = None
_propagate = True  # the package logger's own setting, given back after the last job
_log = logging.getLogger(__name__)


class _RecordingFormatter(logging.Formatter):
    """A warning line that starts with the recording its job reads."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        with _running_lock:
            name = _running.get(record.thread or 0)
            if name is None and len(_running) == 1:
                # a helper thread of the job (the registration's look-ahead)
                (name,) = _running.values()
        return text if name is None or text.startswith(name) else f"{name}: {text}"


@contextlib.contextmanager
def named_warnings(recording: str) -> Iterator[None]:
    """Every warning that afmdrift logs while this thread runs ``recording``'s
    job, and every ``warnings.warn`` in it, printed to stderr as one line that
    starts with ``recording``: in an archive, a warning without its recording
    says nothing. Warnings the filters make errors still raise."""
    global _warning_handler, _propagate
    package = logging.getLogger("afmdrift")
    with _running_lock:
        _running[threading.get_ident()] = recording
        if _warning_handler is None:
            _warning_handler = logging.StreamHandler()
            _warning_handler.setLevel(logging.WARNING)
            _warning_handler.setFormatter(_RecordingFormatter("%(message)s"))
            package.addHandler(_warning_handler)
            _propagate = package.propagate
            package.propagate = False  # one line per warning, the named one
    try:
        with warnings.catch_warnings(record=True) as caught:
            yield
    finally:
        for w in caught:
            _log.warning(
                "%s", warnings.formatwarning(w.message, w.category, w.filename, w.lineno).strip()
            )
        with _running_lock:
            del _running[threading.get_ident()]
            if not _running and _warning_handler is not None:
                package.removeHandler(_warning_handler)
                package.propagate = _propagate
                _warning_handler = None


# --------------------------------------------------------------------------- helpers


def _clear_result(out: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        (out / RESULT_FILE).unlink()


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _one_line(recording: str, err: object) -> str:
    text = " ".join(str(err).split()) or type(err).__name__
    return text if recording in text or Path(recording).name in text else f"{recording}: {text}"


def _frame_reporter(job: Job) -> Callable[[int], None]:
    """A function that reports the frames done in ``job`` to its client (a Dask
    event on ``job.progress_topic``) at most every :data:`PROGRESS_INTERVAL_S`;
    one that does nothing outside a Dask worker or without a topic."""
    from afmdrift.runs._parallel import dask_worker

    worker = dask_worker()
    if not job.progress_topic or worker is None:
        return _no_report
    last = [time.monotonic()]

    def report(frames: int) -> None:
        now = time.monotonic()
        if now - last[0] >= PROGRESS_INTERVAL_S:
            last[0] = now
            worker.log_event(job.progress_topic, {"out": job.out, "frames": frames})

    return report


def _no_report(frames: int) -> None:
    return None


def _worker_address() -> str:
    from afmdrift.runs._parallel import dask_worker

    worker = dask_worker()
    return "local" if worker is None else str(worker.address)


def stems(recordings: Iterable[str]) -> list[str]:
    """A distinct output directory name for each recording, stable for the same
    list: the file or directory name without its suffix, with ``-2``, ``-3``
    ... for a name already taken."""
    taken: dict[str, int] = {}
    out = []
    for rec in recordings:
        p = Path(rec.rstrip("/"))
        base = p.name if p.is_dir() else p.stem
        # a series named by a glob: its name without the pattern's characters
        base = re.sub(r"[*?\[\]]", "", base).strip("._- ") or "recording"
        n = taken.get(base, 0) + 1
        taken[base] = n
        out.append(base if n == 1 else f"{base}-{n}")
    return out
