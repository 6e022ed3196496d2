"""Runs: a recording through the per-frame pipeline, and the run store.

Everything that turns a whole recording into numbers, without the ZeroMQ
daemon: ``afmdrift replay`` (:func:`replay_session`), what the frames of a
session gave the model for ``afmdrift evaluate`` (:func:`measure_session`),
the de-warped frames of ``afmdrift correct`` (:func:`correct_session`), the
drift track of ``afmdrift measure`` and ``afmdrift batch``
(:func:`track_stack`, :func:`track_session`), and the SQLite run store that
the daemon, replay, the dashboard and the diagnostics read and write
(:class:`RunStore`), with the changes of a run's model
(:class:`ModelChange`, :func:`change_terms`, :func:`effective_model`); and
:class:`TaskPool`, which runs a command's independent tasks (diagnose's
online re-runs) on this machine's cores or, inside a Dask worker, on its
cluster. The daemon (:mod:`afmdrift.service`) commits each new
frame through :class:`HeldWrites` (which holds frames in bounded memory while
the store cannot write, a full disk); a replayed recording goes through
:meth:`~afmdrift.pipeline.FramePipeline.run`; both end in
:func:`record_outcome`, so both record exactly the same rows.

Nothing here imports :mod:`afmdrift.service` or ZeroMQ (import-linter keeps
it so), so a Dask worker of ``afmdrift batch`` never loads the daemon.
"""

from afmdrift.runs._changes import (
    PHYSICS_PREDICTORS,
    TERM_COMMANDS,
    ModelChange,
    TermCommand,
    change_terms,
    effective_model,
    model_terms,
)
from afmdrift.runs._correct import CorrectionSummary, correct_session
from afmdrift.runs._csv import TRAJECTORY_COLUMNS, trajectory_rows, write_trajectory_csv
from afmdrift.runs._parallel import TaskPool, available_cores
from afmdrift.runs._record import HeldWrites, process_and_record, record_outcome
from afmdrift.runs._replay import MIN_REPLAY_FRAMES, ReplaySummary, replay_session
from afmdrift.runs._schema import (
    DB_NAME,
    MODEL_CHANGE_COLUMNS,
    STORE_SCHEMA_VERSION,
    StoreError,
    model_change_from_row,
)
from afmdrift.runs._series import measure_session, series_from_drift_log, series_from_records
from afmdrift.runs._snapshot import snapshot_store
from afmdrift.runs._store import RunStore
from afmdrift.runs._track import track_session, track_stack

__all__ = [
    "DB_NAME",
    "MIN_REPLAY_FRAMES",
    "MODEL_CHANGE_COLUMNS",
    "PHYSICS_PREDICTORS",
    "STORE_SCHEMA_VERSION",
    "TERM_COMMANDS",
    "TRAJECTORY_COLUMNS",
    "CorrectionSummary",
    "HeldWrites",
    "ModelChange",
    "ReplaySummary",
    "RunStore",
    "StoreError",
    "TaskPool",
    "TermCommand",
    "available_cores",
    "change_terms",
    "correct_session",
    "effective_model",
    "measure_session",
    "model_change_from_row",
    "model_terms",
    "process_and_record",
    "record_outcome",
    "replay_session",
    "series_from_drift_log",
    "series_from_records",
    "snapshot_store",
    "track_session",
    "track_stack",
    "trajectory_rows",
    "write_trajectory_csv",
]
