"""The instrument interface.

Everything upstream of a driver (registration, models, the service) sees an
instrument only through :class:`Instrument` and the records of
:mod:`afmdrift.records`, whether it is a real NanoScope-style controller, the
simulator, or a replayed session.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import TracebackType
from typing import Literal, Protocol, TypeVar, runtime_checkable

from afmdrift.records import ChannelSample, Event, Frame, InstrumentInfo

__all__ = [
    "CheckedActuator",
    "ConnectOnEnter",
    "EventBacklog",
    "Instrument",
    "Recentre",
    "VelocityActuator",
]


@runtime_checkable
class Instrument(Protocol):
    """What the service needs from an instrument: a real controller, the
    simulator over the wire, or a replayed session.

    All methods are coroutines; implementations serialise access to the
    underlying connection themselves.
    """

    async def connect(self) -> None: ...

    async def close(self) -> None: ...

    async def identify(self) -> InstrumentInfo: ...

    async def now_s(self) -> float:
        """Current instrument time in s."""
        ...

    async def latest_frame(self) -> Frame | None:
        """The last completed frame, or ``None`` before the first one."""
        ...

    async def read_channels(self) -> ChannelSample:
        """Current sensor readings."""
        ...

    async def events(self, start: int = 0) -> list[Event]:
        """Entries ``start, start+1, ...`` of the event log (in log order)."""
        ...

    async def set_offset(self, x_nm: float, y_nm: float) -> None:
        """Command the XY scan offset (absolute, nm). Logged as ``offset_move``."""
        ...

    async def get_offset(self) -> tuple[float, float]: ...


@runtime_checkable
class VelocityActuator(Protocol):
    """An instrument that can move the image at a velocity by itself (an optional
    capability, e.g. a Nanonis controller's ``Piezo.DriftCompSet``).

    The service's closed loop uses it with ``closed_loop_actuator = "velocity"``.
    The displacement the instrument applies must show in :meth:`Instrument.get_offset`
    and in the event log (``offset_move`` entries), like commanded moves, so that
    drift positions stay ``p = m + O(t) − O(t_ref)``.
    """

    async def set_drift_velocity(self, vx_nm_per_s: float, vy_nm_per_s: float) -> None:
        """Move the XY offset at this velocity (nm/s) from now until the next call."""
        ...


@dataclass(frozen=True, slots=True)
class Recentre:
    """A re-centre of the drift compensation, for the image to confirm.

    At ``t_s`` the frame centre took over ``displacement_nm`` (x, y) from the
    compensation, booked as net zero. With ``procedure = "release"`` the
    compensation was switched off and on, booked as releasing the
    displacement (a controller known to reset it); with ``"ramp"`` it was not
    switched, and the displacement was ramped out over the next interval
    between velocity commands (right whatever off does). The frame after it
    must sit where the published d(t) of before put it; under a controller
    that kept the displacement through a ``"release"``, it sits
    ``alternative_jump_nm`` (drift position p, nm) off.
    """

    t_s: float
    displacement_nm: tuple[float, float]
    procedure: Literal["release", "ramp"]
    #: ``"probe"``: a take-over asked for to check the actuator
    #: (:meth:`CheckedActuator.probe`), not needed by the range.
    kind: Literal["recentre", "probe"] = "recentre"

    @property
    def alternative_jump_nm(self) -> tuple[float, float] | None:
        """The jump of the measured drift position if the controller kept a
        displacement booked as released (None: the procedure does not
        depend on it)."""
        if self.procedure == "ramp":
            return None
        # the window stands +q off the books, and content (p = m + O) reads −q
        return (-self.displacement_nm[0], -self.displacement_nm[1])


@runtime_checkable
class CheckedActuator(Protocol):
    """A velocity actuator whose re-centres the daemon checks on the image
    (an optional capability, e.g. the Nanonis driver): it says which
    re-centre waits for its frame, is told what the frame showed, and can be
    told to stop re-centring."""

    recentre_allowed: bool

    @property
    def unchecked_recentre(self) -> Recentre | None: ...

    def recentre_checked(self, *, kept: bool = False) -> None: ...

    async def probe(self, dx_nm: float, dy_nm: float, *, exact: bool = False) -> None: ...


@runtime_checkable
class EventBacklog(Protocol):
    """An instrument whose :meth:`Instrument.events` reads a bounded share of a
    long (or endless) event log per call, and says what it left (an optional
    capability, e.g. the NanoScope-style driver).

    The service holds frames back from the model while the log is behind,
    since commanded moves may be among the entries not read yet, but it no
    longer waits for the log before it measures them.
    """

    #: Entries the last ``events()`` call left unread although the log
    #: announced them (0 when it read the whole log).
    event_backlog: int


class _Connectable(Protocol):
    async def connect(self) -> None: ...

    async def close(self) -> None: ...


_C = TypeVar("_C", bound=_Connectable)


class ConnectOnEnter:
    """Mixin for instruments: ``async with instrument:`` connects on entry and
    closes on exit, whatever happened inside the block."""

    async def __aenter__(self: _C) -> _C:
        await self.connect()
        return self

    async def __aexit__(
        self: _Connectable,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()
