"""Configuration of the drift service (``[service]``).

Times are seconds on the *wall* clock for the service's own loops (offset
stream, heartbeat, polling) and seconds on the *instrument* clock for physical
limits (offset rate of change, staleness), so an accelerated simulator or a
replay behaves like the real instrument.
"""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Literal, Self

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

__all__ = ["ServiceConfig", "check_endpoint", "endpoint_is_local", "host_is_loopback"]


def check_endpoint(endpoint: str) -> str:
    """``endpoint`` if it is a ZeroMQ bind endpoint this service can use, else ValueError.

    ``tcp://HOST:PORT`` (PORT 1–65535, or ``*`` for a free port; an IPv6 HOST
    in brackets), ``ipc://PATH`` or ``inproc://NAME``.
    """
    if endpoint.startswith(("ipc://", "inproc://")):
        if not endpoint.split("://", 1)[1]:
            raise ValueError(f"{endpoint!r}: needs a path or name after the scheme")
        return endpoint
    if not endpoint.startswith("tcp://"):
        raise ValueError(f"{endpoint!r}: use tcp://HOST:PORT, ipc://PATH or inproc://NAME")
    host, sep, port = endpoint[len("tcp://") :].rpartition(":")
    if not sep or not host:
        raise ValueError(f"{endpoint!r}: tcp endpoints are tcp://HOST:PORT")
    if port != "*" and not (port.isdigit() and 1 <= int(port) <= 65535):
        raise ValueError(f"{endpoint!r}: port {port!r} is not 1-65535 or *")
    return endpoint


def endpoint_is_local(endpoint: str) -> bool:
    """True when a ZeroMQ bind endpoint is reachable only from this machine.

    ``ipc://`` and ``inproc://`` are local; ``tcp://HOST:PORT`` is local when
    HOST is ``localhost`` or a loopback address (127.0.0.0/8, ::1). Wildcards
    (``*``, ``0.0.0.0``) and any other interface are not.
    """
    if endpoint.startswith(("ipc://", "inproc://")):
        return True
    if not endpoint.startswith("tcp://"):
        return False
    return host_is_loopback(endpoint[len("tcp://") :].rsplit(":", 1)[0].strip("[]"))


def host_is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback addresses (127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class ServiceConfig(BaseModel):
    """Parameters of the drift daemon (``afmdrift run``) and of replay.

    Binding a socket anywhere but the loopback interface requires ZeroMQ CURVE
    keys (``curve_secret_key_file`` and ``curve_authorized_clients_dir``);
    the configuration is rejected otherwise.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    pub_endpoint: str = Field(
        "tcp://127.0.0.1:5560", description="ZeroMQ PUB bind endpoint (offset/model/frame/status)."
    )
    control_endpoint: str = Field(
        "tcp://127.0.0.1:5561", description="ZeroMQ ROUTER bind endpoint of the control socket."
    )
    curve_secret_key_file: str | None = Field(
        None, description="Server certificate with secret key (zmq.auth.create_certificates)."
    )
    curve_authorized_clients_dir: str | None = Field(
        None, description="Directory of client public certificates allowed to connect."
    )
    control_auth: bool = Field(
        True,
        description="State-changing control commands (pause, resume, reset_reference, "
        "reload_model, add_term, remove_term) need the token in control_token_file.",
    )
    control_token_file: str | None = Field(
        None,
        min_length=1,
        description="Token file written at start-up, readable only by the daemon's user; "
        "default RUN_DIR/control.token. Its directory must exist and be writable.",
    )
    control_max_request_bytes: int = Field(
        65536, ge=256, le=16 << 20, description="Larger control requests are dropped."
    )
    reload_config_dir: str | None = Field(
        None,
        min_length=1,
        description="Directory reload_model may read configuration files from, besides the "
        "directory of the daemon's own configuration file.",
    )
    run_dir: str = Field(
        "runs/latest", min_length=1, description="Run directory (store, archive, logs)."
    )
    archive_frames: bool = Field(False, description="Also keep every image as frames/NNNNNN.npy.")
    archive_corrected: bool = Field(
        False,
        description="Also keep every measured image de-warped by the causal drift trajectory "
        "(each row moved back by the drift at its scan time) as corrected/NNNNNN.npy.",
    )
    store_hold_mb: float = Field(
        64.0,
        ge=1.0,
        le=65536.0,
        description="Memory for frames the run store cannot write yet (a full disk, an I/O "
        "error), MB: they are written once it can again. Past it, images go first, then "
        "whole frames, oldest first; the daemon never stops measuring and publishing.",
    )
    keep_model_states: int = Field(
        100, ge=0, le=10_000_000, description="Predictor states kept in the store (0: all)."
    )
    offset_rate_hz: float = Field(100.0, ge=1.0, le=1000.0, description="Offset stream rate.")
    heartbeat_interval_s: float = Field(1.0, ge=0.05, le=60.0, description="Status period.")
    frame_poll_interval_s: float = Field(0.5, ge=0.005, le=60.0, description="Frame poll period.")
    channel_poll_interval_s: float = Field(5.0, ge=0.01, le=3600.0, description="Channels.")
    event_poll_interval_s: float = Field(1.0, ge=0.01, le=3600.0, description="Event log.")
    clock_sync_interval_s: float = Field(
        1.0, ge=0.01, le=60.0, description="How often the instrument clock is read."
    )
    reconnect_delay_s: float = Field(
        1.0, ge=0.01, le=60.0, description="Wait before reconnecting a failed instrument."
    )
    expected_frame_interval_s: float | None = Field(
        None,
        gt=0,
        description="Instrument seconds between frames; default: learned from the frames.",
    )
    instrument_silence_s: float = Field(
        2.0,
        gt=0,
        le=600.0,
        description="Wall seconds an instrument may leave a request unanswered, no byte "
        "arriving, before offsets are published invalid (flag instrument_silent).",
    )
    stale_factor: float = Field(
        2.0, ge=1.0, le=100.0, description="No frame for this many expected intervals: stale."
    )
    training_window: int = Field(
        50, ge=2, le=10000, description="Observations kept for refits (paper: last 50)."
    )
    min_valid_blocks: int = Field(
        4, ge=1, le=4096, description="Fewer valid blocks: the frame does not feed the model."
    )
    max_offset_nm: float = Field(
        5000.0, gt=0, le=1e6, description="Published offsets are clamped to this magnitude."
    )
    max_offset_rate_nm_s: float = Field(
        5.0, gt=0, le=1e6, description="Largest offset change per instrument second."
    )
    rolling_window: int = Field(
        20, ge=1, le=10000, description="Frames in the rolling prediction error."
    )
    closed_loop: bool = Field(
        False, description="Apply the offset on the instrument (XY-offset command)."
    )
    closed_loop_actuator: Literal["offset", "velocity"] = Field(
        "offset",
        description=(
            "offset: move the XY offset to d(t); velocity: drive the instrument's own drift "
            "compensation with piecewise-constant velocities from d(t) (nanonis://)."
        ),
    )
    closed_loop_interval_s: float = Field(
        1.0, ge=0.01, le=3600.0, description="Wall seconds between closed-loop moves."
    )
    closed_loop_probe_nm: float = Field(
        0.0,
        ge=0.0,
        le=1000.0,
        description=(
            "velocity actuator, off by default: once the model predicts within a quarter of "
            "it, move the frame centre this far across the drift while the compensation ramps "
            "it back out, and check on the next frame (and a second, opposite probe) that the "
            "image did not move. The frame move's own creep and play count against it: on the "
            "simulator with a model without those terms a 20 nm probe read 7 nm."
        ),
    )
    closed_loop_min_step_nm: float = Field(
        0.2, ge=0.0, le=1000.0, description="Smaller corrections are not sent."
    )
    sndhwm: int = Field(
        10000, ge=1, le=10_000_000, description="PUB high-water mark; slow subscribers drop."
    )
    diagnose_every_frames: int = Field(
        10,
        ge=0,
        le=1_000_000,
        description="Diagnose the run (as `afmdrift diagnose RUN_DIR`) in a separate process "
        "after every this many frames, and publish it on topic diagnosis; 0: only on the "
        "diagnose control command.",
    )
    diagnose_timeout_s: float = Field(
        300.0,
        gt=0,
        le=86400.0,
        description="Wall seconds a live diagnosis may take; past it, it is killed, logged "
        "and skipped.",
    )

    @field_validator("pub_endpoint", "control_endpoint")
    @classmethod
    def _check_endpoint(cls, endpoint: str) -> str:
        return check_endpoint(endpoint)

    @property
    def token_path(self) -> Path:
        """The control token file: ``control_token_file``, else ``RUN_DIR/control.token``."""
        return Path(self.control_token_file or Path(self.run_dir) / "control.token")

    @model_validator(mode="after")
    def _require_curve_off_loopback(self) -> Self:
        for key in ("pub_endpoint", "control_endpoint"):
            endpoint = getattr(self, key)
            if endpoint_is_local(endpoint):
                continue
            missing = [
                k
                for k in ("curve_secret_key_file", "curve_authorized_clients_dir")
                if getattr(self, k) is None
            ]
            if missing:
                raise ValueError(
                    f"{key} {endpoint!r} is not a loopback address; binding it requires "
                    f"ZeroMQ CURVE keys: set service.{' and service.'.join(missing)}"
                )
        if self.pub_endpoint == self.control_endpoint and not self.pub_endpoint.endswith(":*"):
            raise ValueError(
                f"pub_endpoint and control_endpoint must differ (both {self.pub_endpoint!r})"
            )
        return self
