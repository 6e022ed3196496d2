"""Read-only access to a run store (``RUN_DIR/run.sqlite``) that a daemon may be writing.

:class:`afmdrift.runs.RunStore` opens its database for writing (it creates
the schema and takes write locks), which a viewer must never do to a live run.
:class:`RunReader` opens the same file with SQLite's ``mode=ro`` URI, so it
can neither write nor lock out the daemon; WAL mode lets it read committed
frames while the daemon appends new ones. Rows become the public
:class:`afmdrift.pipeline.FrameRecord` through the store's own conversion
(:func:`afmdrift.pipeline.record_from_row`), so the schema is described in
one place (``docs/service.md``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import sqlite3
import threading
from pathlib import Path
from typing import Any

from afmdrift.errors import AfmdriftError
from afmdrift.pipeline import FRAME_COLUMNS, FrameRecord, record_from_row
from afmdrift.runs import (
    DB_NAME,
    MODEL_CHANGE_COLUMNS,
    STORE_SCHEMA_VERSION,
    ModelChange,
    model_change_from_row,
)

__all__ = ["DB_FILE", "DashboardError", "RunReader", "StoreNotReadyError", "StoreRows"]

#: Database file of a run directory (``docs/service.md``).
DB_FILE = DB_NAME
#: Store schema this reader understands (``meta.schema_version``).
_SCHEMA_VERSION = str(STORE_SCHEMA_VERSION)
#: Seconds SQLite waits for a writer's checkpoint before giving up on a read.
_BUSY_TIMEOUT_S = 2.0

_COLUMNS = ", ".join(FRAME_COLUMNS)


def _busy(err: sqlite3.DatabaseError) -> bool:
    """SQLite gave up waiting for another connection's lock (``SQLITE_BUSY``)."""
    code = getattr(err, "sqlite_errorcode", None)
    return code is not None and code & 0xFF == sqlite3.SQLITE_BUSY


class DashboardError(AfmdriftError):
    """The dashboard cannot start: unknown run directory, unusable store, bad option."""


class StoreNotReadyError(DashboardError):
    """The run store is not there yet: no run directory, no ``run.sqlite``, a
    database without the store's tables, or one its writer held locked past the
    busy timeout (the daemon creates the directory, then the file, switches it
    to WAL under an exclusive lock, then writes its schema). A dashboard
    following a daemon waits for it; a finished run is refused."""


@dataclasses.dataclass(frozen=True, slots=True)
class StoreRows:
    """What :meth:`RunReader.read_since` found after the given cursors.

    ``channels`` rows are ``(id, t_s, name, value_or_nan)``; ``events`` rows are
    ``(id, epoch, t_s, kind, x_nm, y_nm)``; ``model`` is the newest
    ``(seq, predictor, state)`` when it is newer than the cursor, else ``None``;
    ``meta`` is the whole ``meta`` table (the daemon adds to it after it starts:
    the instrument's identity once connected).
    """

    frames: list[FrameRecord]
    channels: list[tuple[int, float, str, float]]
    events: list[tuple[int, int, float, str, float, float]]
    model: tuple[int, str, dict[str, Any]] | None
    meta: dict[str, str]


class RunReader:
    """Read-only view of ``RUN_DIR/run.sqlite``.

    Parameters
    ----------
    run_dir : path-like
        Run directory written by ``afmdrift run`` or ``afmdrift replay``.

    Raises
    ------
    StoreNotReadyError
        The directory or its ``run.sqlite`` does not exist, or the database has
        no tables yet or stays locked by its writer (a daemon that is creating it).
    DashboardError
        The file is not a run store, or its schema version is not the one
        this reader understands.
    """

    def __init__(self, run_dir: str | Path) -> None:
        self.run_dir = Path(run_dir)
        if not self.run_dir.is_dir():
            raise StoreNotReadyError(f"{self.run_dir}: no such run directory")
        self.path = self.run_dir / DB_FILE
        if not self.path.is_file():
            raise StoreNotReadyError(
                f"{self.run_dir}: not a run directory (no {DB_FILE}; written by afmdrift run "
                "or afmdrift replay)"
            )
        uri = f"{self.path.resolve().as_uri()}?mode=ro"
        self._lock = threading.RLock()
        try:
            self._db = sqlite3.connect(
                uri, uri=True, timeout=_BUSY_TIMEOUT_S, check_same_thread=False
            )
        except sqlite3.Error as err:
            raise DashboardError(f"{self.path}: cannot open read-only ({err})") from None
        try:
            # The daemon creates the file, then its tables in one transaction:
            # a database without tables (an empty file too) is one on its way.
            begun = self._db.execute(
                "SELECT 1 FROM sqlite_master WHERE type = 'table' LIMIT 1"
            ).fetchone()
            if begun is None:
                self._db.close()
                raise StoreNotReadyError(
                    f"{self.path}: no tables yet (afmdrift run creates them when it starts)"
                )
            row = self._db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
            self._db.execute(f"SELECT {_COLUMNS} FROM frames LIMIT 0").fetchall()
        except sqlite3.DatabaseError as err:
            self._db.close()
            if _busy(err):
                raise StoreNotReadyError(
                    f"{self.path}: locked by its writer for over {_BUSY_TIMEOUT_S:g} s ({err}; "
                    "afmdrift run holds it so while it creates the store)"
                ) from None
            raise DashboardError(f"{self.path}: not a usable run store ({err})") from None
        if row is None or str(row[0]) != _SCHEMA_VERSION:
            self._db.close()
            found = "none" if row is None else repr(row[0])
            raise DashboardError(
                f"{self.path}: store schema version {found} is not supported (this dashboard "
                f"reads {_SCHEMA_VERSION})"
            )

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> RunReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def meta(self) -> dict[str, str]:
        """The ``meta`` table as a mapping.

        Raises
        ------
        DashboardError
            The database cannot be read.
        """
        try:
            with self._lock:
                return self._meta()
        except sqlite3.DatabaseError as err:
            raise DashboardError(f"{self.path}: cannot read the run store ({err})") from None

    def _meta(self) -> dict[str, str]:
        return {str(k): str(v) for k, v in self._db.execute("SELECT key, value FROM meta")}

    def frame(self, seq: int) -> FrameRecord | None:
        """One frame record, or ``None``."""
        with self._lock:
            row = self._db.execute(
                f"SELECT {_COLUMNS} FROM frames WHERE seq = ?", (seq,)
            ).fetchone()
        return None if row is None else record_from_row(row)

    def session_reference(self) -> FrameRecord | None:
        """The session reference frame (drift position 0), or ``None`` before it.

        Raises
        ------
        DashboardError
            The database cannot be read.
        """
        try:
            with self._lock:
                row = self._db.execute(
                    f"SELECT {_COLUMNS} FROM frames WHERE reason = 'reference' ORDER BY seq LIMIT 1"
                ).fetchone()
        except sqlite3.DatabaseError as err:
            raise DashboardError(f"{self.path}: cannot read the run store ({err})") from None
        return None if row is None else record_from_row(row)

    def model_changes(self) -> list[ModelChange]:
        """Where the run's model changed (``add_term``, ``remove_term``,
        ``reload_model``), oldest first; empty for a store without the table
        (written before it existed).

        Raises
        ------
        DashboardError
            The database cannot be read.
        """
        try:
            with self._lock:
                have = self._db.execute(
                    "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'model_changes'"
                ).fetchone()
                if have is None:
                    return []
                rows = self._db.execute(
                    f"SELECT {MODEL_CHANGE_COLUMNS} FROM model_changes ORDER BY id"
                ).fetchall()
            return [model_change_from_row(r) for r in rows]
        except (sqlite3.DatabaseError, ValueError) as err:
            raise DashboardError(f"{self.path}: cannot read the run store ({err})") from None

    def stored_curves(self) -> list[tuple[float, dict[str, Any]]]:
        """``(t_end_s, curve)`` of every offset curve kept in the store, oldest first.

        Each curve was published when its frame ended and used until the next
        one; the store keeps the newest ``service.keep_model_states`` of them.
        A damaged row is skipped.

        Raises
        ------
        DashboardError
            The database cannot be read.
        """
        try:
            with self._lock:
                rows = self._db.execute(
                    "SELECT f.t_end_s, m.curve_json FROM model_state m "
                    "JOIN frames f ON f.seq = m.seq "
                    "WHERE m.curve_json IS NOT NULL ORDER BY m.seq"
                ).fetchall()
        except sqlite3.DatabaseError as err:
            raise DashboardError(f"{self.path}: cannot read the run store ({err})") from None
        out: list[tuple[float, dict[str, Any]]] = []
        for t_end, text in rows:
            try:
                curve = json.loads(text)
            except (ValueError, RecursionError):
                continue
            if isinstance(curve, dict) and t_end is not None:
                out.append((float(t_end), curve))
        return out

    def read_since(
        self,
        *,
        frame_seq: int = -1,
        channel_id: int = 0,
        event_id: int = 0,
        model_seq: int = -1,
        max_frames: int | None = None,
    ) -> StoreRows:
        """Rows added after the given cursors, read in one transaction.

        ``max_frames`` keeps only the newest that many frames (the first read
        of a long run).

        Raises
        ------
        DashboardError
            The database cannot be read (removed, corrupted).
        """
        try:
            with self._lock:
                self._db.execute("BEGIN")
                try:
                    return self._rows_since(frame_seq, channel_id, event_id, model_seq, max_frames)
                finally:
                    self._db.execute("COMMIT")
        except (sqlite3.DatabaseError, json.JSONDecodeError) as err:
            raise DashboardError(f"{self.path}: cannot read the run store ({err})") from None

    def _rows_since(
        self,
        frame_seq: int,
        channel_id: int,
        event_id: int,
        model_seq: int,
        max_frames: int | None,
    ) -> StoreRows:
        """:meth:`read_since` inside its transaction, with the lock held."""
        if max_frames is None:
            cur = self._db.execute(
                f"SELECT {_COLUMNS} FROM frames WHERE seq > ? ORDER BY seq", (frame_seq,)
            )
            frames = [record_from_row(r) for r in cur]
        else:
            cur = self._db.execute(
                f"SELECT {_COLUMNS} FROM frames WHERE seq > ? ORDER BY seq DESC LIMIT ?",
                (frame_seq, max_frames),
            )
            frames = [record_from_row(r) for r in cur][::-1]
        channels = [
            (int(i), float(t), str(n), math.nan if v is None else float(v))
            for i, t, n, v in self._db.execute(
                "SELECT id, t_s, name, value FROM channels WHERE id > ? ORDER BY id",
                (channel_id,),
            )
        ]
        events = [
            (int(i), int(e), float(t), str(k), float(x), float(y))
            for i, e, t, k, x, y in self._db.execute(
                "SELECT id, epoch, t_s, kind, x_nm, y_nm FROM events WHERE id > ? ORDER BY id",
                (event_id,),
            )
        ]
        model = None
        row = self._db.execute(
            "SELECT seq, predictor, state_json FROM model_state WHERE seq > ? "
            "ORDER BY seq DESC LIMIT 1",
            (model_seq,),
        ).fetchone()
        if row is not None:
            state = json.loads(row[2])
            model = (int(row[0]), str(row[1]), state if isinstance(state, dict) else {})
        return StoreRows(
            frames=frames, channels=channels, events=events, model=model, meta=self._meta()
        )
