"""Instrument drivers: NanoScope-style controller, simulator, replay.

Runtime code depends only on :class:`Instrument` and the records defined here;
the simulator lives in :mod:`afmdrift.drivers.sim` and is never imported by the
service.
"""

from afmdrift.drivers._base import (
    ChannelSample,
    Event,
    EventKind,
    Frame,
    Instrument,
    InstrumentInfo,
    ScanDirection,
)
from afmdrift.drivers._config import DriverConfig, instrument_from_config
from afmdrift.drivers._nanoscope import NanoScopeDriver
from afmdrift.drivers._protocol import (
    ChecksumError,
    InstrumentDisconnected,
    InstrumentError,
    InstrumentTimeout,
    OutOfSequenceError,
    ProtocolError,
)
from afmdrift.drivers._replay import ReplayInstrument
from afmdrift.drivers._transport import ScriptedTransport, SerialTransport, Transport

__all__ = [
    "ChannelSample",
    "ChecksumError",
    "DriverConfig",
    "Event",
    "EventKind",
    "Frame",
    "Instrument",
    "InstrumentDisconnected",
    "InstrumentError",
    "InstrumentInfo",
    "InstrumentTimeout",
    "NanoScopeDriver",
    "OutOfSequenceError",
    "ProtocolError",
    "ReplayInstrument",
    "ScanDirection",
    "ScriptedTransport",
    "SerialTransport",
    "Transport",
    "instrument_from_config",
]
