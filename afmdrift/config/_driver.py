"""Configuration of the instrument connection (``[driver]``)."""

from __future__ import annotations

import re
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

__all__ = ["FOLDER_PREFIX", "NANONIS_PREFIX", "REPLAY_PREFIX", "DriverConfig"]

#: URL prefix that selects :class:`~afmdrift.drivers.ReplayInstrument`.
REPLAY_PREFIX = "replay:"
#: URL prefix that selects :class:`~afmdrift.drivers.nanonis.NanonisDriver`.
NANONIS_PREFIX = "nanonis://"
_NANONIS_URL = re.compile(r"nanonis://([^:/\s]+):([0-9]{1,5})/?")
_CHANNEL_KEY = re.compile(r"[a-z][a-z0-9_]*")

#: URL prefix that selects :class:`~afmdrift.drivers.FolderInstrument`.
FOLDER_PREFIX = "folder:"


class DriverConfig(BaseModel):
    """How to reach the instrument.

    ``transport`` is a serial port (``/dev/ttyUSB0``), a pseudo-terminal
    (``/dev/pts/5``, e.g. from ``afmdrift sim serve --pty``), loopback TCP
    (``socket://127.0.0.1:5025``, e.g. from ``afmdrift sim serve --port 5025``),
    ``replay:PATH`` to replay a recorded session directory, ``folder:PATH``
    for an AFM whose own software saves each finished image into a folder (the
    ``folder_*`` settings apply to it only), or ``nanonis://HOST:PORT`` for a
    Nanonis controller's TCP interface (the ``nanonis_*`` options apply to it
    only, and are ignored otherwise, so that ``afmdrift run --instrument`` can
    switch transports; ``docs/instruments.md``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    transport: str = Field(
        "socket://127.0.0.1:5025",
        min_length=1,
        description=(
            "Serial port, pty path, socket://HOST:PORT, replay:SESSION_DIR, folder:DIR or "
            "nanonis://HOST:PORT."
        ),
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
    nanonis_channel: int = Field(
        14,
        ge=0,
        le=127,
        description="nanonis: scan channel read by Scan.FrameDataGrab (height, m).",
    )
    nanonis_direction: Literal["forward", "backward"] = Field(
        "forward", description="nanonis: which trace of each line Scan.FrameDataGrab reads."
    )
    nanonis_channels: dict[str, str] = Field(
        default_factory=dict,
        description=(
            "nanonis: afmdrift channel -> Nanonis signal name (Signals.NamesGet), "
            'e.g. {temperature_c = "Temperature (C)"}.'
        ),
    )
    nanonis_offset_mode: Literal["frame", "follow_me"] = Field(
        "frame", description="nanonis: the XY offset moves the scan frame or the follow-me tip."
    )
    nanonis_clock_signal: str = Field(
        "",
        max_length=200,
        description="nanonis: signal giving the instrument time in s; empty: the host clock.",
    )
    nanonis_wait_ms: int = Field(
        200,
        ge=0,
        le=60_000,
        description=(
            "nanonis: timeout of each Scan.WaitEndOfScan (with nanonis_wait_port: how long "
            "each poll waits for the reply of the wait that is always outstanding)."
        ),
    )
    nanonis_wait_port: int | None = Field(
        None,
        ge=1,
        le=65535,
        description=(
            "nanonis: a second port of the controller's TCP interface (it listens on several, "
            "one client each) kept for Scan.WaitEndOfScan, with a wait always outstanding, "
            "so no end of scan is missed. Unset: waits share the command port, and a scan "
            "ending during another command is skipped."
        ),
    )
    nanonis_drift_comp_limit_pct: float = Field(
        10.0, gt=0, le=100, description="nanonis: drift compensation saturation limit, % of range."
    )
    nanonis_drift_comp_release: Literal["unknown", "reset", "keep"] = Field(
        "unknown",
        description=(
            "nanonis: what switching the drift compensation off does to its displacement on "
            "this controller. reset: a re-centre switches it off and on (checked on the next "
            "frame); unknown or keep: a re-centre hands the displacement to the frame centre "
            "and ramps it out over one closed-loop interval, right either way."
        ),
    )
    nanonis_min_recentre_interval_s: float = Field(
        60.0,
        ge=0.0,
        le=86400.0,
        description=(
            "nanonis: instrument seconds at least between two re-centres of the drift "
            "compensation (and none while the last one's check is pending): the bound on "
            "re-centring moves."
        ),
    )

    @field_validator("transport")
    @classmethod
    def _check_transport(cls, url: str) -> str:
        if url.startswith(REPLAY_PREFIX) and not url[len(REPLAY_PREFIX) :].strip():
            raise ValueError("replay: needs a session directory, e.g. replay:runs/session1")
        if url.startswith(FOLDER_PREFIX) and not url[len(FOLDER_PREFIX) :].strip():
            raise ValueError("folder: needs a directory, e.g. folder:/data/afm/today")
        if url.startswith(NANONIS_PREFIX):
            m = _NANONIS_URL.fullmatch(url)
            if m is None or not 0 < int(m.group(2)) < 65536:
                raise ValueError(
                    f"expected nanonis://HOST:PORT with a port in 1..65535, got {url!r}"
                )
        return url

    @field_validator("folder_sensor_file")
    @classmethod
    def _check_sensor_file(cls, name: str) -> str:
        if "/" in name or "\\" in name or name in (".", ".."):
            raise ValueError(f"must be a file name inside the folder, not a path: {name!r}")
        return name

    @field_validator("nanonis_channels")
    @classmethod
    def _check_channels(cls, mapping: dict[str, str]) -> dict[str, str]:
        for key, signal in mapping.items():
            if not _CHANNEL_KEY.fullmatch(key):
                raise ValueError(
                    f"channel name {key!r} must be lower-case snake_case (e.g. temperature_c)"
                )
            if not signal.strip():
                raise ValueError(f"channel {key!r}: the Nanonis signal name is empty")
        return mapping
