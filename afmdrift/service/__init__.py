"""The drift service: asyncio daemon, ZeroMQ publisher, durable run store.

Depends only on the driver interface (:mod:`afmdrift.drivers`), never on the
simulator or the test helpers (enforced by import-linter, see pyproject.toml).

Public API
----------
:class:`DriftService`
    The daemon (``afmdrift run``).
:class:`FramePipeline`, :func:`process_and_record`
    The per-frame pipeline shared by the daemon and replay.
:func:`replay_session`
    ``afmdrift replay``.
:class:`RunStore`, :class:`FrameRecord`
    The SQLite run store.
:class:`ServiceConfig`
    The ``[service]`` configuration section.
Wire format v1 (``docs/wire.md``): :data:`SCHEMA_VERSION`, the message models
and :func:`encode`/:func:`decode`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from afmdrift.service._config import ServiceConfig, endpoint_is_local

if TYPE_CHECKING:
    from afmdrift.service._daemon import INSTRUMENT_ERRORS, DriftService
    from afmdrift.service._pipeline import FrameOutcome, FramePipeline, process_and_record
    from afmdrift.service._replay import ReplaySummary, replay_session
    from afmdrift.service._runner import open_instrument, run_until_signalled
    from afmdrift.service._store import MEASUREMENT_COLUMNS, FrameRecord, RunStore, StoreError
    from afmdrift.service._wire import (
        SCHEMA_VERSION,
        ClockSync,
        ControlReply,
        ControlRequest,
        FieldSummary,
        FrameMsg,
        ModelMsg,
        OffsetMsg,
        StatusMsg,
        WireError,
        decode,
        encode,
    )
    from afmdrift.service._zmq import ServiceSocketError

# The configuration root imports ``ServiceConfig`` from here, and the daemon
# imports the configuration root: everything else loads on first access.
_LAZY = {
    "INSTRUMENT_ERRORS": "_daemon",
    "DriftService": "_daemon",
    "FrameOutcome": "_pipeline",
    "FramePipeline": "_pipeline",
    "process_and_record": "_pipeline",
    "ReplaySummary": "_replay",
    "replay_session": "_replay",
    "open_instrument": "_runner",
    "run_until_signalled": "_runner",
    "MEASUREMENT_COLUMNS": "_store",
    "FrameRecord": "_store",
    "RunStore": "_store",
    "StoreError": "_store",
    "SCHEMA_VERSION": "_wire",
    "ClockSync": "_wire",
    "ControlReply": "_wire",
    "ControlRequest": "_wire",
    "FieldSummary": "_wire",
    "FrameMsg": "_wire",
    "ModelMsg": "_wire",
    "OffsetMsg": "_wire",
    "StatusMsg": "_wire",
    "WireError": "_wire",
    "decode": "_wire",
    "encode": "_wire",
    "ServiceSocketError": "_zmq",
}

__all__ = [
    "INSTRUMENT_ERRORS",
    "MEASUREMENT_COLUMNS",
    "SCHEMA_VERSION",
    "ClockSync",
    "ControlReply",
    "ControlRequest",
    "DriftService",
    "FieldSummary",
    "FrameMsg",
    "FrameOutcome",
    "FramePipeline",
    "FrameRecord",
    "ModelMsg",
    "OffsetMsg",
    "ReplaySummary",
    "RunStore",
    "ServiceConfig",
    "ServiceSocketError",
    "StatusMsg",
    "StoreError",
    "WireError",
    "decode",
    "encode",
    "endpoint_is_local",
    "open_instrument",
    "process_and_record",
    "replay_session",
    "run_until_signalled",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'afmdrift.service' has no attribute {name!r}")
    return getattr(importlib.import_module(f"afmdrift.service.{module}"), name)
