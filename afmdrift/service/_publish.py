"""Publishing: what the daemon says on the wire, and the state it says it from.

:class:`Publishing` owns the PUB socket's messages (wire format v1,
``docs/wire.md``): the offset stream d(t) through the safety limiter, the
``model`` and ``frame`` messages after each frame, and the ``status``
heartbeat with its state and flags (stale, paused, clamped, low confidence,
instrument error, instrument changed, no model). It keeps the per-topic sequence numbers, the
rolling prediction error and the frame timing that staleness is judged by.
"""

from __future__ import annotations

import itertools
import math
import secrets
import statistics
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from afmdrift.config import ServiceConfig
from afmdrift.model import OffsetCurve
from afmdrift.pipeline import FrameOutcome
from afmdrift.service._safety import InstrumentClock, OffsetLimiter, is_stale
from afmdrift.service._zmq import Publisher
from afmdrift.wire import ClockSync, FrameMsg, ModelMsg, OffsetMsg, StatusMsg, TrajectorySample

__all__ = ["OFFSET_CATCH_UP_S", "Publishing"]

State = Literal["starting", "running", "paused", "stale", "stopping"]


#: How late (wall s) an offset sample may come and the stream still catch up
#: with the missed ones (later, it restarts from now: ``dropped_offset_ticks``).
OFFSET_CATCH_UP_S = 0.05


class Publishing:
    """Messages, limiter, flags and status of the drift service.

    Parameters
    ----------
    config : ServiceConfig
    clock : InstrumentClock
        The instrument link's clock (instrument time from wall time).
    flags : set of str
        The service's status flags, shared with the instrument link.
    epoch : callable
        The instrument link's current epoch (carried by every message).
    silent_s : callable
        How long the instrument has left a request unanswered; past
        ``config.instrument_silence_s`` offsets are invalid (flag
        ``instrument_silent``).

    Attributes
    ----------
    curve : OffsetCurve or None
        The d(t) being published.
    paused : bool
        Set by the ``pause`` control command: offsets are published invalid.
    chain : int
        The position chain of the last frame processed (``chain`` on the wire).
    terms : list of str or None
        The physics model's effect terms in use (``terms`` in the status;
        ``None`` for a predictor without terms).
    """

    def __init__(
        self,
        config: ServiceConfig,
        *,
        clock: InstrumentClock,
        flags: set[str],
        epoch: Callable[[], int] = lambda: 0,
        silent_s: Callable[[], float] = lambda: 0.0,
    ) -> None:
        self.config = config
        self.clock = clock
        self.flags = flags
        self.epoch = epoch
        self.silent_s = silent_s
        #: New at every start: a subscriber sees the sequence numbers restart with it.
        self.run_id = secrets.token_hex(8)
        self.last_model: ModelMsg | None = None
        self.dropped_offset_ticks = 0
        self.flags.add("no_model")
        self.state: State = "starting"
        self.paused = False
        self.curve: OffsetCurve | None = None
        self.resumed = False
        self.limiter = OffsetLimiter(
            max_offset_nm=config.max_offset_nm, max_rate_nm_s=config.max_offset_rate_nm_s
        )
        self.last_offset: OffsetMsg | None = None
        self.last_frame_t_s: float | None = None
        self.frames_seen = 0
        self.chain = 0
        self.terms: list[str] | None = None
        self.publisher: Publisher | None = None
        self._frame_ends: deque[float] = deque(maxlen=16)
        self._errors_nm: deque[float] = deque(maxlen=config.rolling_window)
        self._seq = {"offset": 0, "model": 0, "frame": 0, "status": 0}
        #: The frame path's faults (set by the daemon, reported in the status).
        self.faults = PathFaults()

    def _next(self, topic: str) -> int:
        n = self._seq[topic]
        self._seq[topic] = n + 1
        return n

    def recent_errors_nm(self, n: int) -> list[float]:
        """The last ``n`` one-step prediction errors, nm, oldest first."""
        return list(self._errors_nm)[-n:]

    def error_median_nm(self) -> float:
        """Median of the rolling one-step prediction errors, nm (0 before any)."""
        return statistics.median(self._errors_nm) if self._errors_nm else 0.0

    def offset_ticks_skipped(self, n: int) -> None:
        """The offset schedule restarted from now, ``n`` ticks late."""
        self.dropped_offset_ticks += n

    # ------------------------------------------------------------------ frames

    def resume(self, *, frame_ends: list[float], errors_nm: list[float], frames: int) -> None:
        """Continue after a restart from the frames the store committed."""
        self._frame_ends.extend(frame_ends[-16:])
        if frame_ends:
            self.last_frame_t_s = frame_ends[-1]
        self._errors_nm.extend(e for e in errors_nm if math.isfinite(e))
        self.frames_seen = frames
        self.resumed = True
        if self.curve is not None:
            self.flags.discard("no_model")

    def connected(self, t_s: float) -> None:
        """The instrument answered at ``t_s``: staleness counts from the first connection."""
        if self.last_frame_t_s is None and self.config.expected_frame_interval_s is not None:
            self.last_frame_t_s = t_s

    async def frame_done(self, outcome: FrameOutcome, detected_wall_s: float) -> float:
        """Update the state after a processed frame, publish ``model`` (when the
        frame fed the model) and ``frame``; return the frame's latency, s."""
        r = outcome.record
        if outcome.position is not None:
            self.chain = outcome.position.chain
        self._frame_ends.append(r.t_end_s)
        self.last_frame_t_s = r.t_end_s
        if outcome.low_confidence:
            self.flags.add("low_confidence")
        elif r.fed_model:
            self.flags.discard("low_confidence")
        if math.isfinite(r.pred_error_nm):
            self._errors_nm.append(r.pred_error_nm)
        if outcome.curve is not None:
            if self.curve is None and not self.resumed and math.isfinite(r.t_mid_s):
                t_now = self.clock.at(time.time())
                self.limiter.hold(t_now if t_now is not None else r.t_end_s, 0.0, 0.0)
            self.curve = outcome.curve
            self.flags.discard("no_model")
        assert self.publisher is not None
        now = time.time()
        if outcome.curve_dict is not None and r.fed_model:
            await self._publish_model(
                frame=r.seq, t_s=r.t_mid_s, predictor=outcome.predictor_name,
                curve=outcome.curve_dict, wall_s=now, t_fallback_s=r.t_end_s,
            )  # fmt: skip
        latency = time.time() - detected_wall_s
        await self.publisher.send(
            FrameMsg(
                seq=self._next("frame"),
                frame=r.seq,
                instrument_frame=r.instrument_frame,
                t_s=r.t_mid_s,
                wall_s=now,
                dx_nm=_opt(r.dx_nm),
                dy_nm=_opt(r.dy_nm),
                x_nm=_opt(r.x_nm),
                y_nm=_opt(r.y_nm),
                sigma_nm=_opt(r.sigma_nm),
                valid=r.valid,
                fed_model=r.fed_model,
                reason=r.reason,
                valid_blocks=r.valid_blocks,
                total_blocks=r.total_blocks,
                field=outcome.field,
                pred_x_nm=_opt(r.pred_x_nm),
                pred_y_nm=_opt(r.pred_y_nm),
                pred_error_nm=_opt(r.pred_error_nm),
                latency_s=latency,
                trajectory=_samples(outcome),
                run_id=self.run_id,
                epoch=self.epoch(),
                chain=self.chain,
            )
        )
        return latency

    async def model_changed(self, curve: OffsetCurve | None, predictor: str, frame: int) -> None:
        """The model changed between frames (a control command): publish its
        curve, from the last frame processed, ``frame``, on."""
        self.curve = curve
        if curve is None or frame < 0:
            return
        now = time.time()
        t_s = self.clock.at(now)
        await self._publish_model(
            frame=frame, t_s=t_s if t_s is not None else curve.t_valid_s[0], predictor=predictor,
            curve=curve.to_dict(), wall_s=now, t_fallback_s=curve.t_valid_s[0],
        )  # fmt: skip

    async def _publish_model(
        self,
        *,
        frame: int,
        t_s: float,
        predictor: str,
        curve: dict[str, Any],
        wall_s: float,
        t_fallback_s: float,
    ) -> None:
        """Publish a ``model`` message (``t_fallback_s``: the instrument time
        the clock mapping starts from while the clock has no reading yet)."""
        assert self.publisher is not None
        anchor = self.clock.anchor()
        wall, inst, rate = anchor if anchor is not None else (wall_s, t_fallback_s, 1.0)
        self.last_model = ModelMsg(
            seq=self._next("model"),
            frame=frame,
            t_s=t_s,
            wall_s=wall_s,
            predictor=predictor,
            curve=curve,
            clock=ClockSync(wall_s=wall, instrument_s=inst, rate=rate),
            max_offset_nm=self.config.max_offset_nm,
            max_offset_rate_nm_s=self.config.max_offset_rate_nm_s,
            run_id=self.run_id,
            epoch=self.epoch(),
            chain=self.chain,
        )
        await self.publisher.send(self.last_model)

    # ------------------------------------------------------------------ staleness

    def expected_interval_s(self) -> float | None:
        """Configured frame interval, else the median of recent ones (instrument s)."""
        if self.config.expected_frame_interval_s is not None:
            return self.config.expected_frame_interval_s
        if len(self._frame_ends) < 2:
            return None
        diffs = [b - a for a, b in itertools.pairwise(self._frame_ends) if b > a]
        return statistics.median(diffs) if diffs else None

    def stale(self, now_s: float | None) -> bool:
        if now_s is None:
            return False
        return is_stale(
            now_s=now_s,
            last_frame_t_s=self.last_frame_t_s,
            expected_interval_s=self.expected_interval_s(),
            factor=self.config.stale_factor,
        )

    # ------------------------------------------------------------------ offset stream

    def offset_sample(self, wall_s: float, t_s: float | None) -> OffsetMsg:
        """The next offset sample: d(t_s) through the limiter, with its flags.

        Advances the limiter and the sequence number: only the offset loop calls it.
        """
        seq = self._next("offset")
        if t_s is None or self.curve is None:
            return OffsetMsg(
                seq=seq,
                t_s=t_s or 0.0,
                wall_s=wall_s,
                x_nm=0.0,
                y_nm=0.0,
                valid=False,
                run_id=self.run_id,
                epoch=self.epoch(),
                chain=self.chain,
            )
        target = self.curve.at([t_s]).reshape(-1)
        tx, ty = float(target[0]), float(target[1])
        if self.resumed and self.limiter.last is None:
            self.limiter.hold(t_s, tx, ty)  # continue from the resumed model, no ramp
        out = self.limiter.apply(t_s, tx, ty)
        _set_flag(self.flags, "clamped", out.clamped)
        stale = self.stale(t_s)
        _set_flag(self.flags, "stale", stale)
        silent = self.silent_s() > self.config.instrument_silence_s
        _set_flag(self.flags, "instrument_silent", silent)
        valid = not (stale or silent or self.paused or "instrument_error" in self.flags)
        return OffsetMsg(
            seq=seq,
            t_s=t_s,
            wall_s=wall_s,
            x_nm=out.x_nm,
            y_nm=out.y_nm,
            valid=valid,
            clamped=out.clamped,
            run_id=self.run_id,
            epoch=self.epoch(),
            chain=self.chain,
        )

    async def offset_tick(self) -> None:
        """Publish one offset sample (the offset loop's body)."""
        assert self.publisher is not None
        wall = time.time()
        msg = self.offset_sample(wall, self.clock.at(wall))
        self.last_offset = msg
        await self.publisher.send(msg)

    # ------------------------------------------------------------------ status

    def status_msg(self) -> StatusMsg:
        """The next heartbeat (takes the next ``status`` sequence number)."""
        return self._status(self._next("status"))

    def status_snapshot(self) -> StatusMsg:
        """The status now, for a control reply: ``seq`` is the last heartbeat's."""
        return self._status(max(self._seq["status"] - 1, 0))

    def _status(self, seq: int) -> StatusMsg:
        wall = time.time()
        t = self.clock.at(wall)
        flags = set(self.flags)
        if self.paused:
            flags.add("paused")
        if self.stale(t):
            flags.add("stale")
        state: State
        if self.state == "stopping":
            state = "stopping"
        elif self.paused:
            state = "paused"
        elif self.state == "starting":
            state = "starting"
        elif "stale" in flags:
            state = "stale"
        else:
            state = "running"
        errs = list(self._errors_nm)
        return StatusMsg(
            seq=seq,
            t_s=t,
            wall_s=wall,
            state=state,
            flags=sorted(flags),
            frames=self.frames_seen,
            last_frame_t_s=self.last_frame_t_s,
            expected_frame_interval_s=self.expected_interval_s(),
            rolling_error_nm=statistics.fmean(errs) if errs else None,
            rolling_max_error_nm=max(errs) if errs else None,
            rolling_window=self.config.rolling_window,
            dropped_offset_ticks=self.dropped_offset_ticks,
            store_problem=self.faults.store_problem,
            frames_held=self.faults.frames_held,
            frames_unstored=self.faults.frames_unstored,
            frames_failed=self.faults.frames_failed,
            frame_problem=self.faults.frame_problem,
            terms=None if self.terms is None else list(self.terms),
            run_id=self.run_id,
            epoch=self.epoch(),
        )


@dataclass(slots=True)
class PathFaults:
    """What failed on the frame path and has not worked since (the status
    reply's ``store_problem``, ``frame_problem`` and counts)."""

    #: ``"PATH: reason"`` while the run store cannot write.
    store_problem: str | None = None
    #: Frames measured and published but not stored yet (held in memory).
    frames_held: int = 0
    #: Frames measured and published but never stored (let go past the bound).
    frames_unstored: int = 0
    #: Frames whose processing failed (none of their numbers published).
    frames_failed: int = 0
    #: The last frame's failure while it lasts: ``"frame N: reason"``.
    frame_problem: str | None = None


def _set_flag(flags: set[str], name: str, on: bool) -> None:
    if on:
        flags.add(name)
    else:
        flags.discard(name)


def _opt(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _samples(outcome: FrameOutcome) -> list[TrajectorySample]:
    """The frame's trajectory samples for the ``frame`` topic (finite ones)."""
    traj = outcome.trajectory
    if traj is None:
        return []
    out = []
    for k in np.argsort(traj.t_s):
        values = (traj.t_s[k], *traj.xy_nm[k], *traj.sigma_nm[k])
        if all(math.isfinite(float(v)) for v in values):
            t, x, y, sx, sy = (float(v) for v in values)
            out.append(TrajectorySample(t_s=t, x_nm=x, y_nm=y, sigma_x_nm=sx, sigma_y_nm=sy))
    return out
