"""Configuration of the instrument connection (``[driver]``)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator

__all__ = ["FOLDER_PREFIX", "REPLAY_PREFIX", "DriverConfig"]

#: URL prefix that selects :class:`~afmdrift.drivers.ReplayInstrument`.
REPLAY_PREFIX = "replay:"

#: URL prefix that selects :class:`~afmdrift.drivers.FolderInstrument`.
FOLDER_PREFIX = "folder:"


class DriverConfig(BaseModel):
    """How to reach the instrument.

    ``transport`` is a serial port (``/dev/ttyUSB0``), a pseudo-terminal
    (``/dev/pts/5``, e.g. from ``afmdrift sim serve --pty``), loopback TCP
    (``socket://127.0.0.1:5025``, e.g. from ``afmdrift sim serve --port 5025``),
    ``replay:PATH`` to replay a recorded session directory, or ``folder:PATH``
    for an AFM whose own software saves each finished image into a folder
    (``docs/instruments.md``; the ``folder_*`` settings apply to it only).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    transport: str = Field(
        "socket://127.0.0.1:5025",
        min_length=1,
        description="Serial port, pty path, socket://HOST:PORT, replay:SESSION_DIR or folder:DIR.",
    )
    timeout_s: float = Field(2.0, gt=0, le=600, description="Longest wait for a reply line.")
    frame_timeout_s: float = Field(
        60.0, gt=0, le=3600, description="Longest wait for a frame block's payload."
    )
    baudrate: int = Field(115200, ge=300, le=4_000_000, description="Serial line speed.")
    reconnect_attempts: int = Field(
        5, ge=1, le=1000, description="Attempts to (re)open the line before giving up."
    )
    backoff_initial_s: float = Field(
        0.5, gt=0, le=60, description="Wait before the second attempt; doubles each time."
    )
    backoff_max_s: float = Field(30.0, gt=0, le=3600, description="Longest wait between attempts.")
    replay_speed: float = Field(
        1.0,
        ge=0,
        le=1e6,
        description="replay: virtual seconds per wall second; 0 = as fast as frames are polled.",
    )

    folder_poll_s: float = Field(
        0.2,
        ge=0.01,
        le=60,
        description="folder: directory scan period; a file is complete when its size and "
        "mtime are unchanged over two scans.",
    )
    folder_line_time_s: float | None = Field(
        None,
        gt=0,
        le=3600,
        description="folder: time per scan line (s) for files whose header gives none; "
        "without it such a file is timed as scanned in no time, ending at its mtime.",
    )
    folder_channel: str = Field(
        "Height", min_length=1, max_length=100, description="folder: channel read from each file."
    )
    folder_max_header_age_s: float = Field(
        3600.0,
        ge=0,
        le=1e9,
        description="folder: a header time that ends more than this before the file's mtime "
        "(or after it, beyond 60 s of clock skew) is not trusted; the mtime is used.",
    )
    folder_sensor_file: str = Field(
        "sensors.csv",
        min_length=1,
        max_length=255,
        description="folder: name of the sensor log (CSV) inside the folder.",
    )

    @field_validator("transport")
    @classmethod
    def _check_transport(cls, url: str) -> str:
        if url.startswith(REPLAY_PREFIX) and not url[len(REPLAY_PREFIX) :].strip():
            raise ValueError("replay: needs a session directory, e.g. replay:runs/session1")
        if url.startswith(FOLDER_PREFIX) and not url[len(FOLDER_PREFIX) :].strip():
            raise ValueError("folder: needs a directory, e.g. folder:/data/afm/today")
        return url

    @field_validator("folder_sensor_file")
    @classmethod
    def _check_sensor_file(cls, name: str) -> str:
        if "/" in name or "\\" in name or name in (".", ".."):
            raise ValueError(f"must be a file name inside the folder, not a path: {name!r}")
        return name
