"""Safety limits on the published offset, staleness, and the instrument clock.

The offset that reaches a tip controller must never jump: it is clamped in
magnitude (``max_offset_nm``) and in rate of change (``max_offset_rate_nm_s``,
per *instrument* second, so an accelerated simulator is limited like the real
instrument). Stream staleness is judged on the instrument clock too.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

__all__ = ["InstrumentClock", "LimitedOffset", "OffsetLimiter", "is_stale"]


@dataclass(frozen=True, slots=True)
class LimitedOffset:
    """An offset after the limits; ``clamped`` tells whether they changed it."""

    x_nm: float
    y_nm: float
    clamped: bool


class OffsetLimiter:
    """Clamp an offset stream in magnitude and in rate of change.

    Parameters
    ----------
    max_offset_nm : float
        Largest magnitude ``hypot(x, y)`` of the output, nm.
    max_rate_nm_s : float
        Largest change of the output per instrument second, nm/s (Euclidean,
        so the direction of a limited step is preserved).

    Notes
    -----
    The first call sets the output directly (clamped only in magnitude) unless
    :meth:`hold` set a starting point. Time going backwards allows no change.
    """

    def __init__(self, *, max_offset_nm: float, max_rate_nm_s: float) -> None:
        if not (max_offset_nm > 0 and max_rate_nm_s > 0):
            raise ValueError(
                f"limits must be positive, got max_offset_nm={max_offset_nm}, "
                f"max_rate_nm_s={max_rate_nm_s}"
            )
        self.max_offset_nm = float(max_offset_nm)
        self.max_rate_nm_s = float(max_rate_nm_s)
        self._last: tuple[float, float, float] | None = None  # (t_s, x, y)

    @property
    def last(self) -> tuple[float, float] | None:
        """The last output (x_nm, y_nm), or ``None`` before the first."""
        return None if self._last is None else (self._last[1], self._last[2])

    def hold(self, t_s: float, x_nm: float, y_nm: float) -> None:
        """Set the current output (e.g. the offset already applied on the instrument)."""
        x, y, _ = self._clamp_magnitude(float(x_nm), float(y_nm))
        self._last = (float(t_s), x, y)

    def apply(self, t_s: float, x_nm: float, y_nm: float) -> LimitedOffset:
        """Limit the target ``(x_nm, y_nm)`` wanted at instrument time ``t_s``.

        Non-finite targets hold the previous output (flagged as clamped).
        """
        if not (math.isfinite(x_nm) and math.isfinite(y_nm)):
            prev = self.last or (0.0, 0.0)
            if self._last is not None:
                self._last = (max(self._last[0], t_s), prev[0], prev[1])
            return LimitedOffset(prev[0], prev[1], True)
        x, y, clamped = self._clamp_magnitude(float(x_nm), float(y_nm))
        if self._last is not None:
            t0, x0, y0 = self._last
            max_step = self.max_rate_nm_s * max(0.0, t_s - t0)
            dx, dy = x - x0, y - y0
            step = math.hypot(dx, dy)
            if step > max_step:
                scale = max_step / step
                x, y = x0 + dx * scale, y0 + dy * scale
                clamped = True
            t_s = max(t_s, t0)
        self._last = (float(t_s), x, y)
        return LimitedOffset(x, y, clamped)

    def _clamp_magnitude(self, x: float, y: float) -> tuple[float, float, bool]:
        r = math.hypot(x, y)
        if r > self.max_offset_nm:
            s = self.max_offset_nm / r
            return x * s, y * s, True
        return x, y, False


def is_stale(
    *,
    now_s: float,
    last_frame_t_s: float | None,
    expected_interval_s: float | None,
    factor: float,
) -> bool:
    """True when no frame arrived for more than ``factor`` expected intervals.

    All times are instrument seconds; ``last_frame_t_s`` is the end of the last
    frame. Before the interval is known (no configured value, fewer than two
    frames) the stream is not called stale.
    """
    if last_frame_t_s is None or expected_interval_s is None:
        return False
    return now_s - last_frame_t_s > factor * expected_interval_s


class InstrumentClock:
    """Estimate of the instrument clock from the wall clock.

    Reading the instrument clock costs a round trip on the wire, so the service
    reads it every ``clock_sync_interval_s`` and evaluates the offset stream
    at ``at(wall)``: a line through recent (wall, instrument) pairs, whose slope
    is the clock rate (1 for a real instrument, the speed-up of a simulator).
    The estimate never runs backwards.

    Parameters
    ----------
    window : int
        Number of recent readings used for the rate.
    """

    def __init__(self, *, window: int = 16) -> None:
        self._pairs: deque[tuple[float, float]] = deque(maxlen=window)
        self._last_out = -math.inf

    @property
    def synced(self) -> bool:
        return bool(self._pairs)

    def observe(self, *, wall_s: float, instrument_s: float) -> None:
        """Add a reading; an instrument clock that went backwards restarts the fit."""
        if self._pairs and instrument_s < self._pairs[-1][1]:
            self._pairs.clear()
            self._last_out = -math.inf
        self._pairs.append((float(wall_s), float(instrument_s)))

    @property
    def rate(self) -> float:
        """Instrument seconds per wall second (1.0 until two readings exist)."""
        if len(self._pairs) < 2:
            return 1.0
        (w0, i0), (w1, i1) = self._pairs[0], self._pairs[-1]
        if w1 - w0 <= 0 or i1 - i0 <= 0:
            return 1.0
        return (i1 - i0) / (w1 - w0)

    def anchor(self) -> tuple[float, float, float] | None:
        """``(wall_s, instrument_s, rate)`` of the latest reading, or ``None``."""
        if not self._pairs:
            return None
        w, i = self._pairs[-1]
        return w, i, self.rate

    def at(self, wall_s: float) -> float | None:
        """Instrument time at wall time ``wall_s`` (``None`` before any reading)."""
        if not self._pairs:
            return None
        w, i = self._pairs[-1]
        t = i + self.rate * (wall_s - w)
        t = max(t, self._last_out)
        self._last_out = t
        return t
