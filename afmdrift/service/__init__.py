"""The drift service: asyncio daemon and ZeroMQ publisher over the durable run store.

Depends only on the driver interface (:mod:`afmdrift.drivers`), never on the
simulator or the test helpers (enforced by import-linter, see pyproject.toml).

Public API
----------
:class:`DriftService`
    The daemon (``afmdrift run``).
:func:`replay_session`
    ``afmdrift replay`` (defined in :mod:`afmdrift.runs`).
:class:`RunStore`, :class:`FrameRecord`
    The SQLite run store (defined in :mod:`afmdrift.runs` and
    :mod:`afmdrift.pipeline`).
:class:`ServiceConfig`
    The ``[service]`` configuration section (defined in :mod:`afmdrift.config`).

The wire format (``docs/wire.md``) is :mod:`afmdrift.wire`, shared with the
client; the per-frame pipeline is :mod:`afmdrift.pipeline`, and a recording
through it, with the run store, :mod:`afmdrift.runs` (re-exported here for
code written against this package).
"""

from afmdrift.config import ServiceConfig, endpoint_is_local
from afmdrift.pipeline import MEASUREMENT_COLUMNS, FrameRecord
from afmdrift.runs import (
    DB_NAME,
    STORE_SCHEMA_VERSION,
    ReplaySummary,
    RunStore,
    StoreError,
    process_and_record,
    replay_session,
)
from afmdrift.service._check import check_config
from afmdrift.service._daemon import INSTRUMENT_ERRORS, DriftService
from afmdrift.service._live_diagnosis import DIAGNOSES_FILE, last_diagnosis, read_diagnoses
from afmdrift.service._runner import open_instrument, run_until_signalled
from afmdrift.service._safety import OffsetLimiter
from afmdrift.service._zmq import ServiceSocketError

__all__ = [
    "DB_NAME",
    "DIAGNOSES_FILE",
    "INSTRUMENT_ERRORS",
    "MEASUREMENT_COLUMNS",
    "STORE_SCHEMA_VERSION",
    "DriftService",
    "FrameRecord",
    "OffsetLimiter",
    "ReplaySummary",
    "RunStore",
    "ServiceConfig",
    "ServiceSocketError",
    "StoreError",
    "check_config",
    "endpoint_is_local",
    "last_diagnosis",
    "open_instrument",
    "process_and_record",
    "read_diagnoses",
    "replay_session",
    "run_until_signalled",
]
