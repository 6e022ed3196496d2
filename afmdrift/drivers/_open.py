"""Opening the instrument that the ``[driver]`` section describes."""

from __future__ import annotations

from afmdrift.config import FOLDER_PREFIX, REPLAY_PREFIX, DriverConfig
from afmdrift.drivers._base import Instrument
from afmdrift.drivers._folder import FolderInstrument
from afmdrift.drivers._nanoscope import NanoScopeDriver
from afmdrift.drivers._replay import ReplayInstrument
from afmdrift.drivers._transport import SerialTransport

__all__ = ["instrument_from_config"]


def instrument_from_config(config: DriverConfig) -> Instrument:
    """The :class:`Instrument` that ``config`` describes (not yet connected).

    ``replay:PATH`` gives a :class:`~afmdrift.drivers.ReplayInstrument` paced at
    ``replay_speed``; ``folder:DIR`` a :class:`~afmdrift.drivers.FolderInstrument`
    with the ``folder_*`` settings; any other URL a :class:`~afmdrift.drivers.NanoScopeDriver`
    on a :class:`~afmdrift.drivers.SerialTransport`.
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
    return NanoScopeDriver(
        SerialTransport(config.transport, baudrate=config.baudrate),
        timeout_s=config.timeout_s,
        frame_timeout_s=config.frame_timeout_s,
        reconnect_attempts=config.reconnect_attempts,
        backoff_initial_s=config.backoff_initial_s,
        backoff_max_s=config.backoff_max_s,
    )
