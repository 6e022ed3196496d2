"""Session directories (format v1): recorded, simulated or imported AFM sessions;
and drift logs (positions without images)."""

from afmdrift.session._driftlog import DriftLog, is_drift_log, read_drift_log
from afmdrift.session._format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    PRIOR_KEY,
    Session,
    SessionError,
    SessionMeta,
    read_session,
    session_prior_px,
    write_session,
)
from afmdrift.session._import import (
    NoFrameTimingError,
    attach_logs,
    import_files,
    session_from_images,
    stack_session,
)

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "PRIOR_KEY",
    "DriftLog",
    "NoFrameTimingError",
    "Session",
    "SessionError",
    "SessionMeta",
    "attach_logs",
    "import_files",
    "is_drift_log",
    "read_drift_log",
    "read_session",
    "session_from_images",
    "session_prior_px",
    "stack_session",
    "write_session",
]
