"""The records every layer shares: frames, events, channel samples.

The ground floor of the package. A driver produces these records, the session
format stores them, registration and the models read them, and the service
publishes what it computed from them; nothing here imports another afmdrift
module.

Conventions
-----------
* Times ``*_s`` are seconds on the instrument's clock since the session start.
* Heights are in nm. Images are indexed ``[row, col]``; x runs along columns
  (the fast scan axis) and y along rows.
* ``pixel_size_nm`` is ``(x, y)``.
* An ``up`` frame scans rows 0 → N−1, a ``down`` frame N−1 → 0.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from types import MappingProxyType
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

__all__ = [
    "ChannelSample",
    "Event",
    "EventKind",
    "Frame",
    "InstrumentInfo",
    "LoggedEvent",
    "ScanDirection",
    "event_kind",
    "row_times_s",
]


class ScanDirection(StrEnum):
    """Slow-axis direction of a frame."""

    UP = "up"  # rows 0 -> N-1
    DOWN = "down"  # rows N-1 -> 0


class EventKind(StrEnum):
    """Kinds of logged instrument events that afmdrift knows the meaning of.

    The event log is open: a lab's own kinds (``door_open``, ``stage_move``,
    ``tip_approach``, ...) are kept as plain strings (:func:`event_kind`), and
    the generic ``event:`` terms of the physics model can fit a response to
    them. These four keep their documented meaning (``docs/session-format.md``).
    """

    OFFSET_MOVE = "offset_move"  # commanded XY offset moved by (x_nm, y_nm)
    MANIPULATION = "manipulation"  # tip push at (x_nm, y_nm)
    TIP_CHANGE = "tip_change"
    POWER_ON = "power_on"


_KIND_CHARS = frozenset("abcdefghijklmnopqrstuvwxyz0123456789_")
#: Longest accepted event-kind name.
MAX_KIND_LENGTH = 64


def event_kind(text: str) -> EventKind | str:
    """The event kind named by ``text``: a known :class:`EventKind` or the name itself.

    Unknown kinds are kept (the event log of a lab has its own), but the name
    must be a lower-case identifier (letters, digits, ``_``; starting with a
    letter; at most :data:`MAX_KIND_LENGTH` characters) so that it survives
    every format that carries it (CSV, the wire protocol's comma-separated
    fields, term specs such as ``event:door_open``).

    Raises
    ------
    ValueError
        If ``text`` is not such a name; the message quotes it.
    """
    name = text.strip()
    try:
        return EventKind(name)
    except ValueError:
        pass
    if (
        not name
        or len(name) > MAX_KIND_LENGTH
        or not name[0].isalpha()
        or not set(name) <= _KIND_CHARS
    ):
        raise ValueError(
            f"event kind {text[:80]!r} is not a lower-case name of letters, digits and '_' "
            f"starting with a letter (at most {MAX_KIND_LENGTH} characters)"
        )
    return name


@dataclass(frozen=True, slots=True)
class Frame:
    """One completed height image and its timing.

    Attributes
    ----------
    index : int
        Frame number since the session start (0-based, increasing).
    heights_nm : ndarray, shape (rows, cols)
        Heights in nm, float32 or float64, row 0 first whatever the direction.
    pixel_size_nm : (float, float)
        Pixel size along x (columns) and y (rows), in nm.
    t_start_s, t_end_s : float
        Instrument time of the start of the first scanned line and of the end
        of the last one.
    direction : ScanDirection
        Slow-axis direction.
    """

    index: int
    heights_nm: npt.NDArray[np.floating]
    pixel_size_nm: tuple[float, float]
    t_start_s: float
    t_end_s: float
    direction: ScanDirection = ScanDirection.UP

    @property
    def shape(self) -> tuple[int, int]:
        rows, cols = self.heights_nm.shape
        return int(rows), int(cols)

    @property
    def t_mid_s(self) -> float:
        """Mid-scan time, where a frame's drift measurement is placed."""
        return 0.5 * (self.t_start_s + self.t_end_s)

    @property
    def line_time_s(self) -> float:
        """Time per scan line (trace and retrace)."""
        return (self.t_end_s - self.t_start_s) / self.shape[0]

    def row_times_s(self) -> npt.NDArray[np.float64]:
        """Mid-line time of each row ``r`` (indexed as stored), shape (rows,)."""
        return row_times_s(self.t_start_s, self.t_end_s, self.shape[0], self.direction)


def row_times_s(
    t_start_s: float, t_end_s: float, rows: int, direction: ScanDirection
) -> npt.NDArray[np.float64]:
    """Mid-line time of each row of a frame scanned from ``t_start_s`` to
    ``t_end_s`` (indexed as stored: an ``up`` frame's row 0 first, a ``down``
    frame's last), shape (rows,)."""
    order = np.arange(rows, dtype=np.float64)
    if direction is ScanDirection.DOWN:
        order = order[::-1]
    return t_start_s + (order + 0.5) * (t_end_s - t_start_s) / rows


@dataclass(frozen=True, slots=True)
class Event:
    """One entry of the instrument's event log.

    ``kind`` is an :class:`EventKind` or, for a kind afmdrift has no meaning
    for, its name (a string; see :func:`event_kind`). Compare kinds with
    ``==`` or ``is`` against :class:`EventKind` members; ``str(kind)`` is the
    name in either case.
    """

    t_s: float
    kind: EventKind | str
    x_nm: float = 0.0
    y_nm: float = 0.0


@dataclass(frozen=True, slots=True)
class ChannelSample:
    """Logged sensor values at one instant (``temperature_c``, ``humidity_pct``, ...)."""

    t_s: float
    values: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))


@dataclass(frozen=True, slots=True)
class InstrumentInfo:
    """Answer to the identify query."""

    vendor: str
    model: str
    serial: str
    firmware: str


class LoggedEvent(NamedTuple):
    """An event with its place in the instrument's event log.

    ``epoch`` counts instrument restarts seen by the service (0 for a recorded
    session), ``log_index`` is the entry's index in that epoch's log.
    """

    epoch: int
    log_index: int
    event: Event
