"""A consistent copy of a run store that another process is writing.

The daemon commits one transaction per frame while a diagnosis reads its run.
Reading the live file table by table could see frame 41 in ``frames`` and
frame 42's model state; :func:`snapshot_store` instead copies the whole
database with SQLite's online backup API in one step, which holds one read
transaction (a WAL snapshot) for the length of the copy: the copy is the store
as it stood after one commit, and the writer never waits for it (in WAL mode
readers do not block the writer).
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

from afmdrift.runs._schema import DB_NAME, StoreError

__all__ = ["snapshot_store"]

#: How long the copy waits for the writer's lock (only a checkpoint takes it), s.
_BUSY_TIMEOUT_S = 10.0


def snapshot_store(run_dir: str | Path, dest_dir: str | Path) -> tuple[int, int] | None:
    """Copy ``run_dir``'s ``run.sqlite`` to ``dest_dir`` as it stands after one commit.

    Parameters
    ----------
    run_dir : path-like
        A run directory, possibly being written by a daemon.
    dest_dir : path-like
        Where the copy goes (created if needed; a ``run.sqlite`` there is replaced).

    Returns
    -------
    (int, int) or None
        The first and last frame sequence number in the copy, or None when it
        has no frame yet.

    Raises
    ------
    StoreError
        ``run_dir`` holds no run store, or it cannot be read.
    """
    src_path = Path(run_dir) / DB_NAME
    if not src_path.is_file():
        raise StoreError(f"{run_dir}: no run store ({DB_NAME}) to copy")
    dest = Path(dest_dir)
    dest.mkdir(parents=True, exist_ok=True)
    dest_path = dest / DB_NAME
    dest_path.unlink(missing_ok=True)
    uri = f"{src_path.resolve().as_uri()}?mode=ro"
    try:
        src = sqlite3.connect(uri, uri=True, timeout=_BUSY_TIMEOUT_S)
        try:
            out = sqlite3.connect(dest_path)
            try:
                src.backup(out)  # pages=-1: every page in one step, one read transaction
                row = out.execute("SELECT MIN(seq), MAX(seq) FROM frames").fetchone()
            finally:
                out.close()
        finally:
            src.close()
    except sqlite3.DatabaseError as err:
        dest_path.unlink(missing_ok=True)
        raise StoreError(f"{src_path}: cannot copy the run store ({err})") from None
    if row is None or row[0] is None:
        return None
    return int(row[0]), int(row[1])
