"""Opening the instrument that the ``[driver]`` section describes."""

from __future__ import annotations

from afmdrift.config import FOLDER_PREFIX, NANONIS_PREFIX, REPLAY_PREFIX, DriverConfig
from afmdrift.drivers._base import Instrument
from afmdrift.drivers._folder import FolderInstrument
from afmdrift.drivers._nanoscope import NanoScopeDriver
from afmdrift.drivers._replay import ReplayInstrument
from afmdrift.drivers._transport import SerialTransport
from afmdrift.drivers.nanonis import NanonisDriver, nanonis_socket_url

__all__ = ["instrument_from_config"]


def instrument_from_config(config: DriverConfig) -> Instrument:
    """The :class:`Instrument` that ``config`` describes (not yet connected).

    ``replay:PATH`` gives a :class:`~afmdrift.drivers.ReplayInstrument` paced at
    ``replay_speed``; ``folder:DIR`` a :class:`~afmdrift.drivers.FolderInstrument`
    with the ``folder_*`` settings; ``nanonis://HOST:PORT`` a
    :class:`~afmdrift.drivers.nanonis.NanonisDriver` with the ``nanonis_*``
    options; any other URL a :class:`~afmdrift.drivers.NanoScopeDriver` on a
    :class:`~afmdrift.drivers.SerialTransport`.
    """
    if config.transport.startswith(REPLAY_PREFIX):
        path = config.transport[len(REPLAY_PREFIX) :].strip()
        return ReplayInstrument(path, speed=config.replay_speed or None)
    if config.transport.startswith(FOLDER_PREFIX):
        return FolderInstrument(
            config.transport[len(FOLDER_PREFIX) :].strip(),
            poll_s=config.folder_poll_s,
            line_time_s=config.folder_line_time_s,
            channel=config.folder_channel,
            max_header_age_s=config.folder_max_header_age_s,
            sensor_file=config.folder_sensor_file,
        )
    if config.transport.startswith(NANONIS_PREFIX):
        url = nanonis_socket_url(config.transport)
        wait = None
        if config.nanonis_wait_port is not None:
            wait = SerialTransport(f"{url.rsplit(':', 1)[0]}:{config.nanonis_wait_port}")
        return NanonisDriver(
            SerialTransport(url),
            wait_transport=wait,
            channel_index=config.nanonis_channel,
            direction=config.nanonis_direction,
            channels=config.nanonis_channels,
            offset_mode=config.nanonis_offset_mode,
            clock_signal=config.nanonis_clock_signal,
            wait_ms=config.nanonis_wait_ms,
            drift_comp_limit_pct=config.nanonis_drift_comp_limit_pct,
            release=config.nanonis_drift_comp_release,
            min_recentre_interval_s=config.nanonis_min_recentre_interval_s,
            timeout_s=config.timeout_s,
            reconnect_attempts=config.reconnect_attempts,
        )
    return NanoScopeDriver(
        SerialTransport(config.transport, baudrate=config.baudrate),
        timeout_s=config.timeout_s,
        frame_timeout_s=config.frame_timeout_s,
        reconnect_attempts=config.reconnect_attempts,
        backoff_initial_s=config.backoff_initial_s,
        backoff_max_s=config.backoff_max_s,
    )
