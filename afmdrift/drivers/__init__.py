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

__all__ = [
    "ChannelSample",
    "Event",
    "EventKind",
    "Frame",
    "Instrument",
    "InstrumentInfo",
    "ScanDirection",
]
