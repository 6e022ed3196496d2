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

The actuator is checked, not trusted: after a re-centre of the controller's
drift compensation the first frame scanned after it must sit where the
published d(t) of before the re-centre put it (the books say the re-centre
moved nothing). Where it sits where a controller that kept a displacement
booked as released would put it, the driver books it
(:meth:`~afmdrift.drivers.nanonis.NanonisDriver.recentre_checked`); where
neither explains it, or the one-step error grows frame after frame while
the loop acts, the loop raises ``actuator_mismatch`` (status flag, error
log) and falls back to open loop: the velocity is set to zero once, nothing
more is commanded, d(t) is still published. An optional probe
(``closed_loop_probe_nm``) checks the compensation's gain the same way.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
from collections import deque

import numpy as np
import numpy.typing as npt

from afmdrift.config import ServiceConfig
from afmdrift.drivers import CheckedActuator, Recentre, VelocityActuator
from afmdrift.model import (
    OffsetCurve,
    commanded_offset_nm,
    events_of_kind,
    offset_through_play,
    play_gaps,
)
from afmdrift.pipeline import FramePipeline, FrameRecord
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
        # The re-centre waiting for its frame, with d(t) as published before it.
        self._check: tuple[Recentre, OffsetCurve] | None = None
        self._probed = False
        # One-step errors of the frames since the loop first acted.
        self._loop_errors: deque[float] = deque(maxlen=DIVERGE_FRAMES + 1)
        # The first probe's result when it was off (along it, nm, and its
        # displacement): the second, opposite probe decides.
        self._suspect: tuple[float, tuple[float, float]] | None = None
        #: Why the loop fell back to open loop (None: it did not).
        self.fault: str | None = None
        #: Re-centres checked against their frame: (t_s, error vector nm, verdict).
        self.checks: list[tuple[float, tuple[float, float], str]] = []

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

    def frame_done(self, record: FrameRecord) -> None:
        """Check the last re-centre or probe against the first frame scanned
        after it, and the loop for divergence (see the module's docstring)."""
        if self._last_velocity is not None and self.fault is None:
            self._check_divergence(record)
        if self._check is None or not record.valid:
            return
        rc, curve = self._check
        if record.t_start_s < rc.t_s or not (
            math.isfinite(record.x_nm) and math.isfinite(record.y_nm)
        ):
            return
        self._check = None
        actuator = self.link.instrument
        assert isinstance(actuator, CheckedActuator)
        if actuator.unchecked_recentre is not rc:
            return  # settled meanwhile (a saturation the books could not explain)
        t_mid = 0.5 * (record.t_start_s + record.t_end_s)
        pred = curve.at([t_mid]).reshape(-1)
        e = (record.x_nm - float(pred[0]), record.y_nm - float(pred[1]))
        sigma = record.pred_sigma_nm if math.isfinite(record.pred_sigma_nm) else 0.0
        tol = max(CHECK_K * self.publishing.error_median_nm(), CHECK_K * sigma, CHECK_MIN_NM)
        verdict, expected = _verdict(rc, e, tol)
        if rc.kind == "probe":
            tol = max(PROBE_GAIN_TOL * math.hypot(*rc.displacement_nm), CHECK_MIN_NM)
            verdict, expected = self._probe_verdict(rc, e, verdict, expected)
        if verdict == "kept":
            actuator.recentre_checked(kept=True)
        elif verdict != "mismatch":
            actuator.recentre_checked()
        else:
            self._fall_back(
                f"the frame after the {rc.kind} at t = {rc.t_s:.1f} s (frame {record.seq}, "
                f"({rc.displacement_nm[0]:+.1f}, {rc.displacement_nm[1]:+.1f}) nm handed to the "
                f"frame centre) sits ({e[0]:+.1f}, {e[1]:+.1f}) nm off the prediction: {expected} "
                f"(tolerance {tol:.1f} nm)"
            )
        self.checks.append((rc.t_s, e, verdict))
        log.info(
            "closed loop: %s at t = %.1f s checked on frame %d: off by (%.2f, %.2f) nm, %s",
            rc.kind, rc.t_s, record.seq, e[0], e[1], verdict,
        )  # fmt: skip

    def _check_divergence(self, record: FrameRecord) -> None:
        """Errors growing frame after frame while the loop acts (a
        compensation of the wrong sign runs away): open the loop."""
        err = record.pred_error_nm
        if not math.isfinite(err):
            return
        self._loop_errors.append(err)
        last = list(self._loop_errors)
        if len(last) <= DIVERGE_FRAMES or last[-1] < DIVERGE_MIN_NM:
            return
        if all(b >= DIVERGE_FACTOR * a for a, b in itertools.pairwise(last)):
            growth = ", ".join(f"{e:.1f}" for e in last)
            self._fall_back(
                f"the loop diverges: the one-step error grew on each of the last "
                f"{DIVERGE_FRAMES} frames to frame {record.seq} ({growth} nm)"
            )

    def _probe_verdict(
        self, rc: Recentre, e: tuple[float, float], verdict: str, expected: str
    ) -> tuple[str, str]:
        """A probe off the books is first a suspect: the prediction itself
        may be off there (a model of two or three frames on a drift that
        turns). A second probe, the opposite of the first, decides: a
        prediction's error stays, the actuator's flips with the probe, so
        the mean of the two along each probe is the actuator's
        −(1 − g)·|q|."""
        qx, qy = rc.displacement_nm
        size = math.hypot(qx, qy)
        along = (e[0] * qx + e[1] * qy) / size if size > 0 else 0.0
        if self._suspect is None:
            if verdict == "mismatch":
                self._suspect = (along, (qx, qy))
                self._probed = False  # the second goes out at the next tick
                return "suspect", ""
            return verdict, expected
        first, _ = self._suspect
        self._suspect = None
        mean = 0.5 * (first + along)
        if abs(mean) <= max(PROBE_GAIN_TOL * size, CHECK_MIN_NM):
            return "as booked", ""
        return "mismatch", (
            f"{first:+.1f} and {along:+.1f} nm along two opposite probes, {mean:+.1f} nm in "
            f"the mean where the books say 0: the compensation does not apply the velocity asked"
        )

    def _fall_back(self, why: str) -> None:
        """An actuator the daemon cannot explain: alarm, and open loop from now on."""
        self.fault = why
        self.publishing.flags.add("actuator_mismatch")
        actuator = self.link.instrument
        if isinstance(actuator, CheckedActuator):
            actuator.recentre_allowed = False
            actuator.recentre_checked()
        log.error("closed loop: %s; open loop from now on (d(t) is still published)", why)

    async def tick(self) -> None:
        """Move the instrument's XY offset so the image stays on the same spot."""
        if self.fault is not None:
            await self._open_loop()
            return
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
        first = self._last_velocity is None
        self._last_velocity = (t_now, vx, vy)
        if not isinstance(actuator, CheckedActuator):
            return
        size = self.svc.closed_loop_probe_nm
        # Only while the model predicts within the probe's tolerance: its
        # frame then tells the actuator from the prediction.
        recent = self.publishing.recent_errors_nm(PROBE_READY_FRAMES)
        ready = len(recent) == PROBE_READY_FRAMES and max(recent) <= max(
            PROBE_GAIN_TOL * size, CHECK_MIN_NM
        )
        if (
            not first
            and not self._probed
            and size > 0
            and (ready or self._suspect is not None)
            and actuator.unchecked_recentre is None
        ):
            self._probed = True
            if self._suspect is not None:  # the opposite of the first
                qx, qy = self._suspect[1]
                await self.link.call(functools.partial(actuator.probe, exact=True), -qx, -qy)
            else:
                # Across the drift: a prediction's lag lies along it.
                slope = curve.at([t_now + 1.0]).reshape(-1) - curve.at([t_now]).reshape(-1)
                norm = math.hypot(float(slope[0]), float(slope[1]))
                ux, uy = (-float(slope[1]) / norm, float(slope[0]) / norm) if norm else (1.0, 0.0)
                await self.link.call(actuator.probe, size * ux, size * uy)
        rc = actuator.unchecked_recentre
        if rc is not None and (self._check is None or self._check[0] is not rc):
            self._check = (rc, curve)

    async def _open_loop(self) -> None:
        """After a fault: the compensation's velocity to zero, once; nothing else."""
        if self._last_velocity is not None and self._last_velocity[1:] != (0.0, 0.0):
            actuator = self.link.instrument
            assert isinstance(actuator, VelocityActuator)
            await self.link.call(actuator.set_drift_velocity, 0.0, 0.0)
            self._last_velocity = (self._last_velocity[0], 0.0, 0.0)


#: The frame after a re-centre or probe is explained by the books (or by a
#: controller that kept the displacement) when it sits within
#: max(K × the median of the rolling one-step errors, K × the frame's
#: prediction 1σ, the minimum) of where they put it. The median, not the
#: RMS: the slow start's errors are in the window for the first checks. For
#: errors Gaussian in x and y (σ each), the median of their length is
#: 1.18 σ, and a length beyond 4 medians (4.7 σ) has probability 1.6e-5.
CHECK_K = 4.0
CHECK_MIN_NM = 2.0
#: A probe's frame is off the books when it sits more than this fraction of
#: the probe (or :data:`CHECK_MIN_NM`) along it: a compensation gain g with
#: |1 − g| above it.
PROBE_GAIN_TOL = 0.25
#: The probe goes out once this many last one-step errors are all within
#: its tolerance.
PROBE_READY_FRAMES = 2
#: The loop diverges when the one-step error grew by this factor on each of
#: DIVERGE_FRAMES frames in a row, to above DIVERGE_MIN_NM: whatever the
#: cause, it opens.
DIVERGE_FACTOR = 1.5
DIVERGE_FRAMES = 3
DIVERGE_MIN_NM = 10.0


def _verdict(rc: Recentre, e: tuple[float, float], tol: float) -> tuple[str, str]:
    """What the frame after ``rc`` says, off the prediction by ``e`` (nm):
    ``"as booked"``, ``"kept"`` (a displacement booked as released was
    kept), ``"undetermined"`` (too small to tell those apart) or
    ``"mismatch"``; and what was expected, for the alarm.

    A probe is judged along its own direction, across the drift (a
    prediction's lag lies along the drift), against a gain and not the
    rolling errors (a wrong gain inflates those from the loop's first
    command on): the compensation's gain g shows there as −(1 − g)·|q|,
    and |1 − g| above :data:`PROBE_GAIN_TOL` is a mismatch.
    """
    qx, qy = rc.displacement_nm
    size = math.hypot(qx, qy)
    if rc.kind == "probe" and size > 0:
        along = (e[0] * qx + e[1] * qy) / size
        if abs(along) <= max(PROBE_GAIN_TOL * size, CHECK_MIN_NM):
            return "as booked", ""
        return "mismatch", (
            f"{along:+.1f} nm along the probe where the books say 0: the compensation does "
            f"not apply the velocity asked"
        )
    as_booked = math.hypot(*e) <= tol
    alt = rc.alternative_jump_nm
    kept = alt is not None and math.hypot(e[0] - alt[0], e[1] - alt[1]) <= tol
    if as_booked and kept:
        return "undetermined", ""
    if as_booked:
        return "as booked", ""
    if kept:
        return "kept", ""
    if alt is None:
        return "mismatch", "the books say 0"
    return "mismatch", (
        f"the books say 0, and a controller that kept the displacement would put it at "
        f"({alt[0]:+.1f}, {alt[1]:+.1f}) nm"
    )
