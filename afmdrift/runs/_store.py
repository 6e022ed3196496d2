"""The run store: SQLite (WAL) record of everything a run did (the daemon or a replay).

One database ``RUN_DIR/run.sqlite`` per run directory (schema in
``docs/service.md``; the tables and their version in
:mod:`afmdrift.runs._schema`). Each frame is written in a single transaction together
with the channels and events logged since the previous frame, the predictor
state after the frame and the published curve, so a ``kill -9`` at any moment
loses at most the frame being processed, and a restarted service resumes
from the last committed frame. The registration reference image is kept next
to the database (``reference-NNNNNN.npy``, written before and deleted only after a
later reference is committed) so the restarted
tracker measures the next frame against the same image. With
``archive_frames`` every image is kept as ``frames/NNNNNN.npy``.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.model import FrameTrajectory
from afmdrift.pipeline import FrameRecord, ResumeState, record_from_row
from afmdrift.records import ChannelSample, Event, LoggedEvent, event_kind
from afmdrift.runs._changes import ModelChange
from afmdrift.runs._csv import trajectory_rows, write_measurements_csv, write_trajectory_csv
from afmdrift.runs._images import load_reference_image, save_image
from afmdrift.runs._schema import (
    DB_NAME,
    FRAME_FIELDS,
    MODEL_CHANGE_COLUMNS,
    StoreError,
    Transaction,
    meta_get,
    meta_set,
    model_change_from_row,
    model_change_row,
    nan_to_none,
    open_database,
)

__all__ = ["UNSTORED_KEY", "RunStore", "SeqRanges"]

log = logging.getLogger(__name__)

#: ``meta`` key: the frames the daemon measured but could not store (a full
#: disk held them longer than its memory bound), as ``SeqRanges`` text.
UNSTORED_KEY = "unstored_frames"

#: trajectory.csv rows kept while the file cannot be appended to (the table has them all).
_CSV_BACKLOG_ROWS = 100_000


def _json_text(value: dict[str, Any] | str) -> str:
    """``value`` as JSON text (text is taken as serialised already)."""
    return value if isinstance(value, str) else json.dumps(value)


class RunStore:
    """SQLite run store in WAL mode; one instance per process, used from one thread.

    Parameters
    ----------
    run_dir : path-like
        Directory of the run (created if needed).
    archive_frames : bool
        Keep every image as ``frames/NNNNNN.npy``.
    keep_model_states : int
        Keep only the newest this many predictor states (0: keep all). States
        grow with the model's history; the newest one is what a restart needs.
    check_same_thread : bool
        As for :func:`sqlite3.connect`; the daemon opens the store in its main
        thread and then uses it only from its single worker thread.
    """

    def __init__(
        self,
        run_dir: str | Path,
        *,
        archive_frames: bool = False,
        keep_model_states: int = 0,
        check_same_thread: bool = True,
    ) -> None:
        self.run_dir = Path(run_dir)
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise StoreError(f"{self.run_dir}: cannot create run directory ({err})") from None
        self.archive_frames = archive_frames
        self.keep_model_states = keep_model_states
        self.path = self.run_dir / DB_NAME
        try:
            self._db = open_database(self.path, check_same_thread=check_same_thread)
        except StoreError:
            # SQLite says "unable to open database file" or "attempt to write a
            # readonly database" where the directory is the problem: name it.
            if not os.access(self.run_dir, os.W_OK | os.X_OK):
                raise StoreError(
                    f"{self.run_dir}: run directory is not writable ({DB_NAME} and its -wal "
                    "and -shm files are written there)"
                ) from None
            raise
        self._pending_channels: list[ChannelSample] = []
        self._pending_events: list[tuple[int, int, Event]] = []
        # trajectory.csv rows committed but not yet appended (a full disk)
        self._csv_backlog: list[tuple[float, ...]] = []
        self._csv_failing = False

    # ------------------------------------------------------------------ lifecycle

    def close(self) -> None:
        """Write pending channels and events and close the database."""
        if self._pending_channels or self._pending_events:
            with self._transaction():
                self._flush_pending()
        self._db.close()

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ writing

    def set_meta(self, items: dict[str, str]) -> None:
        """Record run-level facts (configuration, instrument identity, source)."""
        with self._transaction():
            for k, v in items.items():
                self._meta_set(k, v)

    def add_channels(self, sample: ChannelSample) -> None:
        """Queue a channel sample; it is committed with the next frame (or on close)."""
        self._pending_channels.append(sample)

    def add_event(self, *, epoch: int, log_index: int, event: Event) -> None:
        """Queue an event-log entry; committed with the next frame (or on close)."""
        self._pending_events.append((epoch, log_index, event))

    def add_model_change(self, change: ModelChange) -> None:
        """Commit one change of the run's model now (its own transaction).

        Raises
        ------
        sqlite3.Error
            The store cannot write; nothing is committed.
        """
        placeholders = ", ".join("?" for _ in MODEL_CHANGE_COLUMNS.split(", "))
        with self._transaction():
            self._db.execute(
                f"INSERT INTO model_changes ({MODEL_CHANGE_COLUMNS}) VALUES ({placeholders})",
                model_change_row(change),
            )

    def record_frame(
        self,
        record: FrameRecord,
        *,
        predictor: str,
        predictor_state: dict[str, Any] | str | None,
        curve: dict[str, Any] | str | None,
        image: npt.NDArray[np.floating] | None = None,
        reference: npt.NDArray[np.floating] | None = None,
        trajectory: FrameTrajectory | None = None,
        corrected: npt.NDArray[np.floating] | None = None,
        channels: Iterable[ChannelSample] = (),
        events: Iterable[LoggedEvent] = (),
        meta: dict[str, str] | None = None,
    ) -> None:
        """Commit one frame atomically with everything queued since the last one.

        ``channels``, ``events`` and ``meta`` are written in the frame's
        transaction too. ``reference`` is the tracker's reference image when it
        changed with this frame; it is written (atomically) before the
        transaction, and the transaction records which frame it belongs to, so
        the two never disagree after a crash. ``predictor_state`` and
        ``curve`` may come serialised already (JSON text: a frame held
        through a full disk keeps them so).

        All or nothing: when a write fails (``sqlite3.Error``, or ``OSError``
        from an image file) nothing of the frame is committed and nothing
        queued is forgotten, so the same call can be made again
        (:class:`~afmdrift.runs.HeldWrites` does, after a full disk). What
        follows the commit (``trajectory.csv``, removing an older reference
        file) never raises: a failure there is logged and retried with the
        next frame.
        """
        if self.archive_frames and image is not None:
            save_image(self.run_dir / "frames" / f"{record.seq:06d}.npy", image)
        if corrected is not None:
            save_image(self.run_dir / "corrected" / f"{record.seq:06d}.npy", corrected)
        if reference is not None:
            save_image(self._reference_path(record.seq), reference)
        with self._transaction():
            self._write_pending(channels, events)
            for k, v in (meta or {}).items():
                self._meta_set(k, v)
            values = [nan_to_none(getattr(record, n)) for n in FRAME_FIELDS]
            placeholders = ", ".join("?" for _ in FRAME_FIELDS)
            self._db.execute(
                f"INSERT INTO frames ({', '.join(FRAME_FIELDS)}) VALUES ({placeholders})",
                values,
            )
            if predictor_state is not None:
                self._db.execute(
                    "INSERT INTO model_state (seq, predictor, state_json, curve_json) "
                    "VALUES (?, ?, ?, ?)",
                    (
                        record.seq,
                        predictor,
                        _json_text(predictor_state),
                        None if curve is None else _json_text(curve),
                    ),
                )
                if self.keep_model_states:
                    self._db.execute(
                        "DELETE FROM model_state WHERE seq NOT IN "
                        "(SELECT seq FROM model_state ORDER BY seq DESC LIMIT ?)",
                        (self.keep_model_states,),
                    )
            samples = [] if trajectory is None else trajectory_rows(record.seq, trajectory)
            self._db.executemany(
                "INSERT INTO trajectory (t_s, x_nm, y_nm, sigma_x_nm, sigma_y_nm, seq) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                [tuple(nan_to_none(v) for v in r) for r in samples],
            )
            if reference is not None:
                self._meta_set("reference_seq", str(record.seq))
                self._meta_set("reference_x_nm", repr(record.image_x_nm))
                self._meta_set("reference_y_nm", repr(record.image_y_nm))
        self._pending_channels.clear()
        self._pending_events.clear()
        # The committed samples, also as a file a user can open while the run
        # goes on (the table stays the record).
        self._csv_backlog.extend(samples)
        self._append_trajectory_csv()
        if reference is not None:
            # Only now is the new reference committed; older images can go.
            keep = self._reference_path(record.seq)
            for old in self.run_dir.glob("reference-*.npy"):
                if old != keep:
                    try:
                        old.unlink(missing_ok=True)
                    except OSError as err:
                        log.warning("run store: cannot remove %s (%s)", old, err)

    def _append_trajectory_csv(self) -> None:
        """Append the committed samples not yet in ``trajectory.csv``; on a
        failure (a full disk) they wait for the next frame."""
        if not self._csv_backlog:
            return
        path = self.run_dir / "trajectory.csv"
        size = path.stat().st_size if path.exists() else None
        try:
            write_trajectory_csv(path, self._csv_backlog, append=True)
        except OSError as err:
            _truncate(path, size)  # no half-written line stays behind
            if not self._csv_failing:
                log.warning("run store: cannot append to %s (%s); retried with the next frame",
                            path, err)  # fmt: skip
            self._csv_failing = True
            del self._csv_backlog[: max(0, len(self._csv_backlog) - _CSV_BACKLOG_ROWS)]
            return
        self._csv_backlog.clear()
        self._csv_failing = False

    def _reference_path(self, seq: int) -> Path:
        return self.run_dir / f"reference-{seq:06d}.npy"

    # ------------------------------------------------------------------ reading

    def frame_count(self) -> int:
        row = self._db.execute("SELECT COUNT(*) FROM frames").fetchone()
        return int(row[0])

    def frames(self, *, since_seq: int = -1) -> list[FrameRecord]:
        """All frame records with ``seq > since_seq``, in order."""
        cur = self._db.execute(
            f"SELECT {', '.join(FRAME_FIELDS)} FROM frames WHERE seq > ? ORDER BY seq",
            (since_seq,),
        )
        return [record_from_row(row) for row in cur]

    def last_frames(self, n: int) -> list[FrameRecord]:
        """The last ``n`` frame records, oldest first."""
        cur = self._db.execute(
            f"SELECT {', '.join(FRAME_FIELDS)} FROM frames ORDER BY seq DESC LIMIT ?", (n,)
        )
        return [record_from_row(row) for row in cur][::-1]

    def channels(self) -> list[ChannelSample]:
        """Committed channel samples in time order (one sample per distinct time)."""
        out: list[ChannelSample] = []
        cur = self._db.execute("SELECT t_s, name, value FROM channels ORDER BY id")
        for t_s, name, value in cur:
            v = float("nan") if value is None else float(value)
            if out and out[-1].t_s == t_s:
                merged = dict(out[-1].values)
                merged[name] = v
                out[-1] = ChannelSample(t_s=t_s, values=merged)
            else:
                out.append(ChannelSample(t_s=float(t_s), values={name: v}))
        return out

    def events(self, *, epoch: int | None = None) -> list[LoggedEvent]:
        """Committed events as ``(epoch, log_index, Event)`` in log order."""
        query = "SELECT epoch, log_index, t_s, kind, x_nm, y_nm FROM events"
        args: tuple[Any, ...] = ()
        if epoch is not None:
            query += " WHERE epoch = ?"
            args = (epoch,)
        cur = self._db.execute(query + " ORDER BY epoch, log_index", args)
        return [
            LoggedEvent(
                int(e),
                int(i),
                Event(t_s=float(t), kind=event_kind(k), x_nm=float(x), y_nm=float(y)),
            )
            for e, i, t, k, x, y in cur
        ]

    def model_changes(self) -> list[ModelChange]:
        """The run's model changes, oldest first (``docs/service.md``)."""
        cur = self._db.execute(f"SELECT {MODEL_CHANGE_COLUMNS} FROM model_changes ORDER BY id")
        return [model_change_from_row(row) for row in cur]

    def curve(self, seq: int) -> dict[str, Any] | None:
        row = self._db.execute(
            "SELECT curve_json FROM model_state WHERE seq = ?", (seq,)
        ).fetchone()
        if row is None or row[0] is None:
            return None
        doc: dict[str, Any] = json.loads(row[0])
        return doc

    def meta(self) -> dict[str, str]:
        return {k: v for k, v in self._db.execute("SELECT key, value FROM meta")}

    def resume_state(self) -> ResumeState | None:
        """State to resume from, or ``None`` for an empty store."""
        last = self.last_frames(1)
        if not last:
            return None
        predictor, state, curve = self._latest_model_state()
        meta = self.meta()
        reference_seq = _meta_int(meta, "reference_seq")
        reference = (
            None
            if reference_seq is None
            else load_reference_image(self._reference_path(reference_seq))
        )
        cursor_row = self._db.execute(
            "SELECT MAX(epoch), MAX(log_index) FROM events WHERE epoch = "
            "(SELECT MAX(epoch) FROM events)"
        ).fetchone()
        event_cursor = 0 if cursor_row[1] is None else int(cursor_row[1]) + 1
        return ResumeState(
            last=last[0],
            predictor=predictor,
            predictor_state=state,
            curve=curve,
            reference=reference,
            reference_seq=reference_seq if reference is not None else None,
            reference_record=None if reference is None else self._frame_record(reference_seq),
            reference_x_nm=float(meta.get("reference_x_nm", "nan")),
            reference_y_nm=float(meta.get("reference_y_nm", "nan")),
            event_cursor=event_cursor,
            epoch=last[0].epoch,
            t_ref_s=self._session_reference_time(),
        )

    def _frame_record(self, seq: int | None) -> FrameRecord | None:
        if seq is None:
            return None
        row = self._db.execute(
            f"SELECT {', '.join(FRAME_FIELDS)} FROM frames WHERE seq = ?", (seq,)
        ).fetchone()
        return None if row is None else record_from_row(row)

    def _latest_model_state(self) -> tuple[str, dict[str, Any] | None, dict[str, Any] | None]:
        """``(predictor, state, curve)`` of the newest readable model-state row.

        A row whose JSON is damaged is reported and skipped; an older one is
        used instead (``("", None, None)`` when none is readable).
        """
        rows = self._db.execute(
            "SELECT seq, predictor, state_json, curve_json FROM model_state ORDER BY seq DESC"
        )
        for seq, predictor, state_json, curve_json in rows:
            try:
                state = json.loads(state_json)
                curve = None if curve_json is None else json.loads(curve_json)
            except (TypeError, ValueError, RecursionError) as err:
                log.warning("run store: model state of frame %s is damaged (%s); skipped", seq, err)
                continue
            if not isinstance(state, dict) or not (curve is None or isinstance(curve, dict)):
                log.warning("run store: model state of frame %s is not an object; skipped", seq)
                continue
            return str(predictor), state, curve
        return "", None, None

    def _session_reference_time(self) -> float | None:
        """Mid-scan time of the session reference frame (where p = 0)."""
        row = self._db.execute(
            "SELECT t_mid_s FROM frames WHERE reason = 'reference' ORDER BY seq LIMIT 1"
        ).fetchone()
        return None if row is None else float(row[0])

    def check_consistency(self) -> list[str]:
        """Problems found in the store (empty when consistent): integrity, gaps, orphans."""
        problems: list[str] = []
        ok = self._db.execute("PRAGMA integrity_check").fetchone()[0]
        if ok != "ok":
            problems.append(f"integrity_check: {ok}")
        seqs = [int(r[0]) for r in self._db.execute("SELECT seq FROM frames ORDER BY seq")]
        # frames the daemon measured but had to let go (a full disk) are no gap
        unstored = SeqRanges.parse(meta_get(self._db, UNSTORED_KEY) or "")
        if seqs and [s for s in range(seqs[0], seqs[-1] + 1) if s not in unstored] != seqs:
            problems.append("frames: sequence numbers have gaps")
        orphans = self._db.execute(
            "SELECT COUNT(*) FROM model_state WHERE seq NOT IN (SELECT seq FROM frames)"
        ).fetchone()[0]
        if orphans:
            problems.append(f"model_state: {orphans} rows without a frame")
        return problems

    def write_measurements_csv(self, path: str | Path | None = None) -> Path:
        """Write ``measurements.csv`` (columns
        :data:`~afmdrift.pipeline.MEASUREMENT_COLUMNS`) atomically."""
        out = Path(path) if path is not None else self.run_dir / "measurements.csv"
        return write_measurements_csv(out, self.frames())

    # ------------------------------------------------------------------ internals

    def _transaction(self) -> Transaction:
        return Transaction(self._db)

    def _meta_set(self, key: str, value: str) -> None:
        meta_set(self._db, key, value)

    def _flush_pending(self) -> None:
        self._write_pending((), ())
        self._pending_channels.clear()
        self._pending_events.clear()

    def _write_pending(
        self, channels: Iterable[ChannelSample], events: Iterable[LoggedEvent]
    ) -> None:
        """Insert the queued channels and events and the given ones (inside the
        caller's transaction; the queues are cleared once it commits)."""
        rows = [
            (s.t_s, name, nan_to_none(float(v)))
            for s in itertools.chain(self._pending_channels, channels)
            for name, v in s.values.items()
        ]
        self._db.executemany("INSERT INTO channels (t_s, name, value) VALUES (?, ?, ?)", rows)
        self._db.executemany(
            "INSERT OR IGNORE INTO events (epoch, log_index, t_s, kind, x_nm, y_nm) "
            "VALUES (?, ?, ?, ?, ?, ?)",
            [
                (epoch, idx, e.t_s, str(e.kind), e.x_nm, e.y_nm)
                for epoch, idx, e in itertools.chain(self._pending_events, events)
            ],
        )


def _truncate(path: Path, size: int | None) -> None:
    """Put ``path`` back to ``size`` bytes (``None``: it did not exist)."""
    try:
        if size is None:
            path.unlink(missing_ok=True)
        else:
            os.truncate(path, size)
    except OSError as err:
        log.warning("run store: cannot restore %s after a failed write (%s)", path, err)


def _meta_int(meta: dict[str, str], key: str) -> int | None:
    try:
        return int(meta[key])
    except (KeyError, ValueError):
        return None


class SeqRanges:
    """A set of frame numbers kept as ranges, written ``"3-7,12"``."""

    def __init__(self, ranges: list[list[int]] | None = None) -> None:
        self._ranges: list[list[int]] = ranges or []

    @classmethod
    def parse(cls, text: str) -> SeqRanges:
        out: list[list[int]] = []
        for part in filter(None, (p.strip() for p in text.split(","))):
            a, _, b = part.partition("-")
            try:
                out.append([int(a), int(b or a)])
            except ValueError:
                log.warning("run store: %s entry %r is not a frame range; ignored",
                            UNSTORED_KEY, part)  # fmt: skip
        return cls(out)

    def add(self, seq: int) -> None:
        if self._ranges and self._ranges[-1][1] + 1 == seq:
            self._ranges[-1][1] = seq
        elif seq not in self:
            self._ranges.append([seq, seq])

    def __contains__(self, seq: object) -> bool:
        return any(a <= seq <= b for a, b in self._ranges)  # type: ignore[operator]

    def __len__(self) -> int:
        return sum(b - a + 1 for a, b in self._ranges)

    def text(self) -> str:
        return ",".join(str(a) if a == b else f"{a}-{b}" for a, b in self._ranges)
