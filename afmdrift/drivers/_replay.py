"""Replay a recorded session directory through the :class:`Instrument` interface.

:class:`ReplayInstrument` plays a session (format v1, ``docs/session-format.md``)
on a virtual clock, so the service cannot tell it from a live instrument:

* frame ``i`` becomes the latest completed frame when the clock reaches its
  ``t_end_s``;
* channels are linearly interpolated at the current time;
* recorded events appear in the log once the clock passes their time;
* :meth:`set_offset` is logged as an ``offset_move`` event (with the delta, as a
  controller logs it) and :meth:`get_offset` returns it, but a replayed session
  cannot move: the recorded images do not change.

Clock
-----
With ``speed`` > 0 the clock runs ``speed`` times wall time from
:meth:`connect`: ``t = start_s + speed · (wall() − wall0)``, where ``start_s``
defaults to the first frame's ``t_start_s``. With ``speed=None`` (or 0) the
replay runs as fast as its consumer: each :meth:`latest_frame` call completes
the next frame and moves the clock to its ``t_end_s``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from types import MappingProxyType

import numpy as np

from afmdrift._version import __version__
from afmdrift.drivers._base import ConnectOnEnter
from afmdrift.records import ChannelSample, Event, EventKind, Frame, InstrumentInfo
from afmdrift.session import Session, read_session

__all__ = ["ReplayInstrument"]


class ReplayInstrument(ConnectOnEnter):
    """A recorded session behaving as an instrument.

    Parameters
    ----------
    session : Session or path-like
        A :class:`~afmdrift.session.Session` or a session directory.
    speed : float or None
        Virtual seconds per wall second; ``None`` or 0 for as fast as the
        consumer polls (one new frame per :meth:`latest_frame` call).
    clock : callable
        Wall clock in s (default :func:`time.monotonic`); tests pass their own.
    start_s : float, optional
        Virtual time at :meth:`connect` (default: the first frame's ``t_start_s``).
    """

    def __init__(
        self,
        session: Session | str | Path,
        *,
        speed: float | None = 1.0,
        clock: Callable[[], float] = time.monotonic,
        start_s: float | None = None,
    ) -> None:
        if speed is not None and not (np.isfinite(speed) and speed >= 0):
            raise ValueError(f"speed must be >= 0 or None, got {speed!r}")
        self.session: Session = session if isinstance(session, Session) else read_session(session)
        self.source = str(session) if not isinstance(session, Session) else self.session.meta.source
        self.speed = None if not speed else float(speed)
        self._clock = clock
        n = len(self.session)
        self._t_end = self.session.frame_times[:, 1].copy() if n else np.zeros(0)
        first = float(self.session.frame_times[0, 0]) if n else 0.0
        self.start_s = first if start_s is None else float(start_s)
        self._recorded = sorted(self.session.events, key=lambda e: e.t_s)
        self._wall0: float | None = None
        self._asap_t = self.start_s
        self._asap_next = 0  # next frame to complete in as-fast-as-possible mode
        self._latest: Frame | None = None
        self._log: list[Event] = []
        self._revealed = 0
        self._offset = (0.0, 0.0)

    # ---------------------------------------------------------------- lifecycle

    async def connect(self) -> None:
        """Start the replay clock (idempotent)."""
        if self._wall0 is None:
            self._wall0 = self._clock()

    async def close(self) -> None:
        return None

    def _now(self) -> float:
        if self.speed is None:
            return self._asap_t
        if self._wall0 is None:
            return self.start_s
        return self.start_s + self.speed * (self._clock() - self._wall0)

    @property
    def finished(self) -> bool:
        """Every recorded frame has completed."""
        n = len(self.session)
        if self.speed is None:
            return self._asap_next >= n
        return n == 0 or self._now() >= float(self._t_end[-1])

    # ---------------------------------------------------------------- Instrument

    async def identify(self) -> InstrumentInfo:
        name = Path(self.source).name if self.source else "session"
        return InstrumentInfo(
            vendor="afmdrift", model="ReplayInstrument", serial=name, firmware=__version__
        )

    async def now_s(self) -> float:
        return self._now()

    def _frame(self, i: int) -> Frame:
        f = self.session.frame(i)
        return Frame(
            index=f.index,
            heights_nm=np.array(f.heights_nm),  # a private copy, not a view of the file
            pixel_size_nm=f.pixel_size_nm,
            t_start_s=f.t_start_s,
            t_end_s=f.t_end_s,
            direction=f.direction,
        )

    async def latest_frame(self) -> Frame | None:
        """The last frame whose ``t_end_s`` has passed (as-fast-as-possible: the next one)."""
        if self.speed is None:
            if self._asap_next < len(self.session):
                self._latest = self._frame(self._asap_next)
                self._asap_t = max(self._asap_t, self._latest.t_end_s)
                self._asap_next += 1
            return self._latest
        done = int(np.searchsorted(self._t_end, self._now(), side="right")) - 1
        if done < 0:
            return None
        if self._latest is None or self._latest.index != done:
            self._latest = self._frame(done)
        return self._latest

    async def read_channels(self) -> ChannelSample:
        """Every recorded channel, linearly interpolated at now (held at the ends)."""
        t = self._now()
        s = self.session
        if s.channel_t_s.size == 0:
            return ChannelSample(t_s=t)
        values = {name: float(np.interp(t, s.channel_t_s, col)) for name, col in s.channels.items()}
        return ChannelSample(t_s=t, values=MappingProxyType(values))

    def _reveal(self) -> None:
        t = self._now()
        while self._revealed < len(self._recorded) and self._recorded[self._revealed].t_s <= t:
            self._log.append(self._recorded[self._revealed])
            self._revealed += 1

    async def events(self, start: int = 0) -> list[Event]:
        """Recorded events up to now, merged in time order with offsets set during replay."""
        if start < 0:
            raise ValueError(f"events: start must be >= 0, got {start}")
        self._reveal()
        return self._log[start:]

    async def set_offset(self, x_nm: float, y_nm: float) -> None:
        """Log an ``offset_move`` (delta from the previous offset); the images do not move."""
        for name, v in (("x_nm", x_nm), ("y_nm", y_nm)):
            if not np.isfinite(v):
                raise ValueError(f"set_offset: {name} = {v!r} is not finite")
        self._reveal()
        dx, dy = float(x_nm) - self._offset[0], float(y_nm) - self._offset[1]
        self._offset = (float(x_nm), float(y_nm))
        self._log.append(Event(t_s=self._now(), kind=EventKind.OFFSET_MOVE, x_nm=dx, y_nm=dy))

    async def get_offset(self) -> tuple[float, float]:
        return self._offset
