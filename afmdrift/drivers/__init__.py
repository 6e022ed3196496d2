"""Instrument drivers: NanoScope-style controller, Nanonis (:mod:`.nanonis`), folder of
saved images, simulator, replay.

Runtime code depends only on :class:`Instrument` and the records of
:mod:`afmdrift.records` (re-exported here);
the simulator lives in :mod:`afmdrift.drivers.sim` and is never imported by the
service.
"""

from afmdrift.config import DriverConfig
from afmdrift.drivers._base import (
    CheckedActuator,
    EventBacklog,
    Instrument,
    Recentre,
    VelocityActuator,
)
from afmdrift.drivers._folder import FolderInstrument, OffsetNotSupportedError
from afmdrift.drivers._nanoscope import NanoScopeDriver
from afmdrift.drivers._open import instrument_from_config
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
from afmdrift.records import ChannelSample, Event, EventKind, Frame, InstrumentInfo, ScanDirection

__all__ = [
    "ChannelSample",
    "CheckedActuator",
    "ChecksumError",
    "DriverConfig",
    "Event",
    "EventBacklog",
    "EventKind",
    "FolderInstrument",
    "Frame",
    "Instrument",
    "InstrumentDisconnected",
    "InstrumentError",
    "InstrumentInfo",
    "InstrumentTimeout",
    "NanoScopeDriver",
    "OffsetNotSupportedError",
    "OutOfSequenceError",
    "ProtocolError",
    "Recentre",
    "ReplayInstrument",
    "ScanDirection",
    "ScriptedTransport",
    "SerialTransport",
    "Transport",
    "VelocityActuator",
    "instrument_from_config",
]
