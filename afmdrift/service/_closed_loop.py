"""Closed loop: the daemon moves the instrument's XY offset so the image stays put.

With ``service.closed_loop`` the daemon's ``closed`` loop calls
:meth:`ClosedLoop.tick` every ``closed_loop_interval_s``: the instrument's
offset is set to the offset it had at the reference frame plus the published
d(t), through the play of the offset actuator when the model has fitted one
(``closed_loop_actuator = "offset"``), or a velocity is set that keeps the
offset on that path (``"velocity"``, an instrument's own drift compensation).

When the position chain changes (``Publishing.chain``: a new reference whose
position was estimated) or the instrument was found to be another one
(:meth:`ClosedLoop.rebaseline`), the loop does not act on the difference:
it takes the instrument's offset as it stands, less d(t) now, as the new
offset at the reference, and follows only how d moves from there.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import numpy.typing as npt

from afmdrift.config import ServiceConfig
from afmdrift.drivers import VelocityActuator
from afmdrift.model import commanded_offset_nm, events_of_kind, offset_through_play, play_gaps
from afmdrift.pipeline import FramePipeline
from afmdrift.records import EventKind
from afmdrift.service._acquire import Acquisition
from afmdrift.service._link import InstrumentLink
from afmdrift.service._publish import Publishing

__all__ = ["ClosedLoop"]

log = logging.getLogger(__name__)


class ClosedLoop:
    """Applies the published offset on the instrument (one tick at a time).

    Parameters
    ----------
    svc : ServiceConfig
        ``closed_loop_actuator``, ``closed_loop_min_step_nm``,
        ``max_offset_rate_nm_s``.
    link, acquisition, publishing, pipeline
        The daemon's parts: the instrument, its event log, the published
        offset and curve, and the model (its reference time and offset play).

    Attributes
    ----------
    absolute_offset_base : tuple of float or None
        The instrument's absolute offset before any logged move (set when it
        connects, :meth:`connected`).
    """

    def __init__(
        self,
        svc: ServiceConfig,
        *,
        link: InstrumentLink,
        acquisition: Acquisition,
        publishing: Publishing,
        pipeline: FramePipeline,
    ) -> None:
        self.svc = svc
        self.link = link
        self.acquisition = acquisition
        self.publishing = publishing
        self.pipeline = pipeline
        self.absolute_offset_base: tuple[float, float] | None = None
        self._last_command: tuple[float, float] | None = None
        # offset_move steps of the event log (n, 2), and the log length they are of
        self._play_steps: tuple[int, npt.NDArray[np.float64]] = (-1, np.zeros((0, 2)))
        self._last_velocity: tuple[float, float, float] | None = None  # t_s, vx, vy
        # The chain the hold is for, the hold taken at a chain change (None:
        # the offset at the session reference), and a re-baseline asked for.
        self._chain = 0
        self._hold: tuple[float, float] | None = None
        self._rebaseline = False

    def rebaseline(self) -> None:
        """Take the instrument's offset as it stands as the baseline at the
        next tick (another instrument answers: its offset is not the one the
        hold was taken from)."""
        self._rebaseline = True

    def connected(self, t_s: float, offset: tuple[float, float]) -> None:
        """The instrument connected with absolute ``offset`` at ``t_s``."""
        moved = commanded_offset_nm([t_s], self.acquisition.events)[0]
        self.absolute_offset_base = (offset[0] - moved[0], offset[1] - moved[1])

    def hold_offset(self) -> tuple[float, float] | None:
        """The instrument's absolute offset at the reference frame (where d = 0
        puts it; after a chain change, the baseline taken then), or ``None``
        while there is no valid prediction to follow."""
        last = self.publishing.last_offset
        base = self.absolute_offset_base
        if last is None or not last.valid or base is None or self.publishing.curve is None:
            return None
        if self._hold is not None:
            return self._hold
        t_ref = self.pipeline.t_ref_s
        if t_ref is None:
            return None
        moved_ref = commanded_offset_nm([t_ref], self.acquisition.events)[0]
        return base[0] + moved_ref[0], base[1] + moved_ref[1]

    async def tick(self) -> None:
        """Move the instrument's XY offset so the image stays on the same spot."""
        hold = self.hold_offset()
        if hold is not None and (self._rebaseline or self.publishing.chain != self._chain):
            hold = await self._take_baseline()
        if self.svc.closed_loop_actuator == "velocity":
            await self._velocity_tick(hold)
            return
        last = self.publishing.last_offset
        if hold is None or last is None:
            return
        x = hold[0] + last.x_nm
        y = hold[1] + last.y_nm
        x, y = self._through_play(x, y)
        if (
            self._last_command is not None
            and math.hypot(x - self._last_command[0], y - self._last_command[1])
            < self.svc.closed_loop_min_step_nm
        ):
            return
        await self.link.set_offset(x, y)
        self._last_command = (x, y)

    async def _take_baseline(self) -> tuple[float, float]:
        """The hold at a chain change: the instrument's offset now less the
        published d now, so the jump between the chains moves nothing."""
        last = self.publishing.last_offset
        assert last is not None
        ox, oy = await self.link.call(self.link.instrument.get_offset)
        self._hold = (ox - last.x_nm, oy - last.y_nm)
        self._last_command = (ox, oy)
        self._chain, self._rebaseline = self.publishing.chain, False
        log.info(
            "closed loop: position chain %d: the offset (%.3f, %.3f) nm is the new baseline",
            self._chain, ox, oy,
        )  # fmt: skip
        return self._hold

    def _through_play(self, x: float, y: float) -> tuple[float, float]:
        """The offset to command so the image lands where ``(x, y)`` would put
        it without the play hysteresis of the offset actuator (the model's
        ``hysteresis`` term, when fitted).

        d(t) already holds the play gap after the moves the model has seen;
        what the moves since then, and this one, change in it is added here
        (:func:`~afmdrift.model.step_through_play`). Moves sent but not yet
        back in the event log count as one step.
        """
        play = self.pipeline.predictor.offset_play()
        base = self.absolute_offset_base
        if play is None or base is None:
            return x, y
        events = self.acquisition.events
        if self._play_steps[0] != len(events):
            self._play_steps = (len(events), events_of_kind(events, EventKind.OFFSET_MOVE)[1])
        steps = self._play_steps[1]
        logged = np.asarray(base) + steps.sum(axis=0)
        sent = np.asarray(self._last_command) if self._last_command is not None else logged
        seen = self.pipeline.history.of_kind(EventKind.OFFSET_MOVE)[1]
        out = []
        for axis, want in enumerate((x, y)):
            g_now = play_gaps(np.append(steps[:, axis], sent[axis] - logged[axis]), play.play_nm)
            g_seen = play_gaps(seen[:, axis], play.play_nm)
            out.append(
                offset_through_play(
                    want,
                    sent=float(sent[axis]),
                    gap_nm=float(g_now[-1]),
                    gap_seen_nm=float(g_seen[-1]) if g_seen.size else 0.0,
                    play_nm=play.play_nm,
                    gain=play.gain[axis],
                )
            )
        return out[0], out[1]

    async def _velocity_tick(self, hold: tuple[float, float] | None) -> None:
        """Drive the instrument's own drift compensation: a piecewise-constant
        velocity that keeps the offset on ``hold + d(t)``.

        ``v = (hold + d(t + τ) − offset(t))/τ``, with τ three tick intervals
        (of instrument time, measured): the slope of d is fed forward, so a
        ramp is followed without lag, and an error (a new d(t) after a frame,
        a ramp booked late) decays with time constant τ. (With τ one frame
        period, as before, a correction published at the end of a frame was
        only a third applied by the middle of the next.) Three ticks keep the
        loop stable when a command waits one tick behind a frame transfer: a
        gain of 1/3 per tick, where an integrating loop with one tick of delay
        oscillates from 1. The velocity is limited to ``max_offset_rate_nm_s``;
        without a valid prediction it is set to zero once.
        """
        actuator = self.link.instrument
        assert isinstance(actuator, VelocityActuator)
        curve = self.publishing.curve
        if hold is None or curve is None:
            if self._last_velocity is not None and self._last_velocity[1:] != (0.0, 0.0):
                await self.link.call(actuator.set_drift_velocity, 0.0, 0.0)
                self._last_velocity = (self._last_velocity[0], 0.0, 0.0)
            return
        t_now = await self.link.now_s()
        ox, oy = await self.link.call(actuator.get_offset)
        prev = self._last_velocity
        tick = t_now - prev[0] if prev is not None and t_now > prev[0] else 1.0
        tau = 3.0 * tick
        target = curve.at([t_now + tau]).reshape(-1)
        vx = (hold[0] + float(target[0]) - ox) / tau
        vy = (hold[1] + float(target[1]) - oy) / tau
        speed = math.hypot(vx, vy)
        limit = self.svc.max_offset_rate_nm_s
        if speed > limit:
            vx, vy = vx * limit / speed, vy * limit / speed
        await self.link.call(actuator.set_drift_velocity, vx, vy)
        self._last_velocity = (t_now, vx, vy)
