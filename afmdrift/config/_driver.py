"""Configuration of the instrument connection (``[driver]``)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator

__all__ = ["REPLAY_PREFIX", "DriverConfig"]

#: URL prefix that selects :class:`~afmdrift.drivers.ReplayInstrument`.
REPLAY_PREFIX = "replay:"


class DriverConfig(BaseModel):
    """How to reach the instrument.

    ``transport`` is a serial port (``/dev/ttyUSB0``), a pseudo-terminal
    (``/dev/pts/5``, e.g. from ``afmdrift sim serve --pty``), loopback TCP
    (``socket://127.0.0.1:5025``, e.g. from ``afmdrift sim serve --port 5025``),
    or ``replay:PATH`` to replay a recorded session directory.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    transport: str = Field(
        "socket://127.0.0.1:5025",
        min_length=1,
        description="Serial port, pty path, socket://HOST:PORT, or replay:SESSION_DIR.",
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

    @field_validator("transport")
    @classmethod
    def _check_transport(cls, url: str) -> str:
        if url.startswith(REPLAY_PREFIX) and not url[len(REPLAY_PREFIX) :].strip():
            raise ValueError("replay: needs a session directory, e.g. replay:runs/session1")
        return url
