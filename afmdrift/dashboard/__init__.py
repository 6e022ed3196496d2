"""Live dashboard in the browser: ``afmdrift dashboard`` (``docs/dashboard.md``).

A client of the daemon's published topics (``docs/wire.md``) and a read-only
reader of its run store (``docs/service.md``); it changes nothing in the
daemon. Also opens a finished run directory.

Public API
----------
:class:`Dashboard`
    The server: follows a daemon and/or a run store, serves the page.
:class:`RunReader`
    Read-only access to ``RUN_DIR/run.sqlite`` while a daemon writes it.
:class:`RunState`, :class:`Envelope`
    The bounded in-memory state and the min/max envelope behind it.
:class:`ArrayTruth`, :class:`FunctionTruth`, :class:`TruthSource`, :func:`load_session`
    True drift for simulated or recorded sessions.
:class:`DashboardError`
    Unusable input (run directory, store, endpoint, address, token).
:class:`StoreNotReadyError`
    The run store does not exist yet (a live dashboard waits for it).
"""

from afmdrift.dashboard._app import Dashboard
from afmdrift.dashboard._envelope import Envelope
from afmdrift.dashboard._sources import load_session
from afmdrift.dashboard._state import ArrayTruth, FunctionTruth, RunState, TruthSource
from afmdrift.dashboard._store import DashboardError, RunReader, StoreNotReadyError

__all__ = [
    "ArrayTruth",
    "Dashboard",
    "DashboardError",
    "Envelope",
    "FunctionTruth",
    "RunReader",
    "RunState",
    "StoreNotReadyError",
    "TruthSource",
    "load_session",
]
