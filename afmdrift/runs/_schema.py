"""The run store's database: its tables, its version, and how it is opened.

One SQLite database ``RUN_DIR/run.sqlite`` (:data:`DB_NAME`) per run
directory, in WAL mode with ``synchronous=FULL``; its tables are described in
``docs/service.md``. The ``frames`` table has one column per field of
:class:`~afmdrift.pipeline.FrameRecord`, so the record and the table cannot
disagree. A store of an older version this one can read is brought up to
date when it is opened; any other version is refused.
"""

from __future__ import annotations

import contextlib
import json
import math
import sqlite3
import time
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path
from typing import Any

from afmdrift.errors import AfmdriftError
from afmdrift.pipeline import FRAME_COLUMNS, FrameRecord
from afmdrift.runs._changes import ModelChange

__all__ = [
    "DB_NAME",
    "FRAME_FIELDS",
    "MODEL_CHANGE_COLUMNS",
    "STORE_SCHEMA_VERSION",
    "StoreError",
    "Transaction",
    "meta_get",
    "meta_set",
    "model_change_from_row",
    "model_change_row",
    "nan_to_none",
    "open_database",
]

STORE_SCHEMA_VERSION = 2
#: File name of the run store inside a run directory.
DB_NAME = "run.sqlite"

#: Columns of the ``frames`` table, in :class:`FrameRecord` order.
FRAME_FIELDS = FRAME_COLUMNS
_SQL_TYPES = {"int": "INTEGER", "float": "REAL", "str": "TEXT", "bool": "INTEGER"}


class StoreError(AfmdriftError):
    """The run store cannot be opened or is not a store this version can read."""


def _schema() -> list[str]:
    cols = []
    for f in fields(FrameRecord):
        sql_type = _SQL_TYPES[str(f.type)]
        # REAL columns hold NULL for a value that does not exist (NaN in Python).
        suffix = " PRIMARY KEY" if f.name == "seq" else "" if sql_type == "REAL" else " NOT NULL"
        cols.append(f"{f.name} {sql_type}{suffix}")
    return [
        "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
        f"CREATE TABLE IF NOT EXISTS frames ({', '.join(cols)})",
        "CREATE TABLE IF NOT EXISTS channels (id INTEGER PRIMARY KEY, t_s REAL NOT NULL, "
        "name TEXT NOT NULL, value REAL)",
        "CREATE TABLE IF NOT EXISTS events (id INTEGER PRIMARY KEY, epoch INTEGER NOT NULL, "
        "log_index INTEGER NOT NULL, t_s REAL NOT NULL, kind TEXT NOT NULL, "
        "x_nm REAL NOT NULL, y_nm REAL NOT NULL, UNIQUE (epoch, log_index))",
        "CREATE TABLE IF NOT EXISTS model_state (seq INTEGER PRIMARY KEY "
        "REFERENCES frames(seq), predictor TEXT NOT NULL, state_json TEXT NOT NULL, "
        "curve_json TEXT)",
        "CREATE INDEX IF NOT EXISTS channels_t ON channels (t_s)",
        "CREATE TABLE IF NOT EXISTS trajectory (seq INTEGER NOT NULL REFERENCES frames(seq), "
        "t_s REAL NOT NULL, x_nm REAL, y_nm REAL, sigma_x_nm REAL, sigma_y_nm REAL)",
        # Added within version 2: a store without it has had no model change,
        # and a reader that does not know it is not disturbed by it.
        f"CREATE TABLE IF NOT EXISTS model_changes (id INTEGER PRIMARY KEY, "
        f"{', '.join(f'{n} {t}' for n, t in _CHANGE_COLUMNS)})",
    ]


#: Columns of the ``model_changes`` table, in :class:`ModelChange` order
#: (the terms as JSON lists, NULL for a predictor without terms).
_CHANGE_COLUMNS = (
    ("seq", "INTEGER NOT NULL"),
    ("t_s", "REAL"),
    ("wall_s", "REAL NOT NULL"),
    ("command", "TEXT NOT NULL"),
    ("term", "TEXT"),
    ("predictor", "TEXT NOT NULL"),
    ("terms_before", "TEXT"),
    ("terms_after", "TEXT"),
    ("handover_until_s", "REAL"),
    ("step_bound_nm", "REAL"),
)
#: ``SELECT`` list of the ``model_changes`` table for :func:`model_change_from_row`.
MODEL_CHANGE_COLUMNS = ", ".join(n for n, _ in _CHANGE_COLUMNS)


def model_change_row(change: ModelChange) -> tuple[Any, ...]:
    """The ``model_changes`` row of ``change`` (columns :data:`MODEL_CHANGE_COLUMNS`)."""

    def terms(v: tuple[str, ...] | None) -> str | None:
        return None if v is None else json.dumps(list(v))

    return (
        change.seq,
        nan_to_none(change.t_s),
        change.wall_s,
        change.command,
        change.term,
        change.predictor,
        terms(change.terms_before),
        terms(change.terms_after),
        nan_to_none(change.handover_until_s),
        nan_to_none(change.step_bound_nm),
    )


def model_change_from_row(row: Sequence[Any]) -> ModelChange:
    """A :class:`ModelChange` from a row of :data:`MODEL_CHANGE_COLUMNS`."""
    seq, t_s, wall_s, command, term, predictor, before, after, until_s, bound_nm = row

    def real(v: Any) -> float:
        return math.nan if v is None else float(v)

    def terms(text: str | None) -> tuple[str, ...] | None:
        return None if text is None else tuple(str(t) for t in json.loads(text))

    return ModelChange(
        seq=int(seq),
        t_s=real(t_s),
        wall_s=float(wall_s),
        command=str(command),
        term=None if term is None else str(term),
        predictor=str(predictor),
        terms_before=terms(before),
        terms_after=terms(after),
        handover_until_s=real(until_s),
        step_bound_nm=real(bound_nm),
    )


def open_database(path: Path, *, check_same_thread: bool = True) -> sqlite3.Connection:
    """Open (or create) the store at ``path``, at :data:`STORE_SCHEMA_VERSION`.

    The connection is in autocommit mode: writes go through :class:`Transaction`.

    Raises
    ------
    StoreError
        Not a database, or a schema version this one cannot read.
    """
    try:
        db = sqlite3.connect(path, isolation_level=None, check_same_thread=check_same_thread)
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=FULL")
        db.execute("PRAGMA foreign_keys=ON")
        with Transaction(db):
            for stmt in _schema():
                db.execute(stmt)
            version = meta_get(db, "schema_version")
            if version is None:
                meta_set(db, "schema_version", str(STORE_SCHEMA_VERSION))
                meta_set(db, "created_unix_s", repr(time.time()))
            elif int(version) == 1:
                # Version 2 added the observation each frame fed the model
                # (obs_*) and the trajectory table (created above).
                have = {r[1] for r in db.execute("PRAGMA table_info(frames)")}
                for name in ("obs_t_s", "obs_x_nm", "obs_y_nm", "obs_sigma_nm"):
                    if name not in have:
                        db.execute(f"ALTER TABLE frames ADD COLUMN {name} REAL")
                meta_set(db, "schema_version", str(STORE_SCHEMA_VERSION))
            elif int(version) != STORE_SCHEMA_VERSION:
                raise StoreError(
                    f"{path}: store schema version {version} is not supported "
                    f"(this version writes {STORE_SCHEMA_VERSION})"
                )
    except sqlite3.DatabaseError as err:
        raise StoreError(f"{path}: not a usable run store ({err})") from None
    return db


class Transaction:
    """``BEGIN IMMEDIATE`` ... ``COMMIT`` (``ROLLBACK`` on error) on an autocommit connection."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __enter__(self) -> None:
        self._db.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            try:
                self._db.execute("COMMIT")
            except sqlite3.Error:
                self._rollback()  # a COMMIT that failed (a full disk) leaves nothing
                raise
        else:
            self._rollback()

    def _rollback(self) -> None:
        # SQLite ends the transaction itself on some errors (a full disk):
        # then there is nothing to roll back, and the caller must see the
        # error that happened, not this one.
        if self._db.in_transaction:
            with contextlib.suppress(sqlite3.Error):
                self._db.execute("ROLLBACK")


def meta_get(db: sqlite3.Connection, key: str) -> str | None:
    """The value of ``key`` in the ``meta`` table, or None."""
    row = db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
    return None if row is None else str(row[0])


def meta_set(db: sqlite3.Connection, key: str, value: str) -> None:
    """Set ``key`` in the ``meta`` table (inside the caller's transaction)."""
    db.execute(
        "INSERT INTO meta (key, value) VALUES (?, ?) "
        "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
        (key, value),
    )


def nan_to_none(v: Any) -> Any:
    """NaN and infinities as SQL NULL (a value that does not exist)."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v
