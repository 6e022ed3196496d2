"""The predictor interface shared by every drift model.

A predictor sees the cumulative drift position p(t) (nm, registration sign
convention, commanded offset moves already removed) one frame at a time, with
the logged channels and events, and predicts p at any later time.
"""

from __future__ import annotations

import abc
import bisect
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from afmdrift.model._denoise import SmoothedChannel, smooth_channel
from afmdrift.records import ChannelSample, Event, EventKind, ScanDirection

__all__ = [
    "History",
    "Observation",
    "OffsetPlay",
    "Prediction",
    "Predictor",
    "events_of_kind",
    "scan_samples",
]

#: Sample times per scan window of a measurement that averages over one (the
#: midpoint rule: a 128 s frame is sampled every 8 s, finer than a lab's
#: sensor log, so a channel's changes within the scan are followed).
WINDOW_SAMPLES = 16


def scan_samples(
    t_s: npt.ArrayLike, window_s: npt.ArrayLike | None = None, *, k: int = WINDOW_SAMPLES
) -> npt.NDArray[np.float64]:
    """The times at which a model is evaluated to predict each measurement, shape (n, m).

    A raster frame's drift position is not p at one instant: each line is
    scanned at its own time, and registration averages the lines, so the
    position is the mean of p over the frame's scan window. ``window_s``
    (n, 2) gives ``(t_start_s, t_end_s)`` per measurement; rows with a finite
    window of positive length are sampled at the ``k`` midpoints of equal
    parts of it, the others (point measurements, NaN windows) at ``t_s``.
    Without any window the result is ``t_s`` as one column (m = 1).
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    if window_s is None:
        return t[:, None].copy()
    w = np.asarray(window_s, dtype=np.float64).reshape(-1, 2)
    if w.shape[0] != t.size:
        raise ValueError(f"{w.shape[0]} scan windows for {t.size} times")
    span = w[:, 1] - w[:, 0]
    windowed = np.isfinite(span) & (span > 0)
    if not np.any(windowed):
        return t[:, None].copy()
    frac = (np.arange(k, dtype=np.float64) + 0.5) / k
    out = np.repeat(t[:, None], k, axis=1)
    out[windowed] = w[windowed, :1] + span[windowed, None] * frac[None, :]
    return out


@dataclass(frozen=True, slots=True)
class Observation:
    """One frame's drift measurement as a model sees it.

    Attributes
    ----------
    t_s : float
        Mid-scan time of the frame (instrument clock, s).
    x_nm, y_nm : float
        Cumulative drift position p at ``t_s`` relative to the session's
        reference, with commanded offset moves removed.
    sigma_nm : float
        Standard uncertainty of each coordinate, nm.
    direction : ScanDirection
        Slow-scan direction of the frame (for the scan-direction bias).
    frame : int
        Frame index.
    reference_direction : ScanDirection or None
        Slow-scan direction of the session reference the position is measured
        against (``None``: unknown). A scan-direction bias cancels between
        frames of the reference's direction, so the drift itself
        (:meth:`Predictor.predict_drift`) is the position such a frame would
        show; unknown, it is the midpoint between up and down frames.
    window_s : (float, float) or None
        Scan window ``(t_start_s, t_end_s)`` the position averages over (a
        whole frame's position is the mean of p over the lines it scanned,
        :func:`scan_samples`); ``None``: a measurement at the instant ``t_s``.
    """

    t_s: float
    x_nm: float
    y_nm: float
    sigma_nm: float
    direction: ScanDirection = ScanDirection.UP
    frame: int = -1
    reference_direction: ScanDirection | None = None
    window_s: tuple[float, float] | None = None

    @staticmethod
    def window_of(row: npt.ArrayLike | None) -> tuple[float, float] | None:
        """A scan window ``(t_start_s, t_end_s)`` from a table row, None where
        the row is absent or not finite (a point measurement)."""
        if row is None:
            return None
        w = np.asarray(row, dtype=np.float64).reshape(2)
        return (float(w[0]), float(w[1])) if np.all(np.isfinite(w)) else None

    def samples(self) -> npt.NDArray[np.float64]:
        """Times at which p is averaged to predict this measurement, shape (m,)."""
        window = None if self.window_s is None else [self.window_s]
        return np.asarray(scan_samples([self.t_s], window)[0], dtype=np.float64)


def events_of_kind(
    events: Sequence[Event], kind: EventKind | str
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Times (n,) and ``(x_nm, y_nm)`` (n, 2) of the events of ``kind`` in
    ``events``, in time order (stable for equal times)."""
    ev = [e for e in events if e.kind == kind]
    t = np.array([e.t_s for e in ev], dtype=np.float64)
    xy = np.array([(e.x_nm, e.y_nm) for e in ev], dtype=np.float64).reshape(-1, 2)
    order = np.argsort(t, kind="stable")
    return t[order], xy[order]


@dataclass(frozen=True, slots=True)
class OffsetPlay:
    """Fitted play (backlash) of the offset actuator (the ``hysteresis`` term).

    After a commanded step Δ the scanner's gap to the command is
    ``g' = clip(g − Δ, −play_nm, play_nm)`` (:func:`afmdrift.model.play_gaps`),
    and the measured position p moves by ``gain·g`` per axis (−1 for a
    scanner that lags its command by the play, the image moving with the
    scanner; 0 on an axis where the fit found no hysteresis).
    """

    play_nm: float
    gain: tuple[float, float]


@dataclass(slots=True)
class History:
    """Append-only log of channel samples and events that models read.

    :meth:`channel_at` gives the values as logged, interpolated linearly inside
    the log and held at the last value beyond it. :meth:`sensed_at` gives the
    quantity the sensor measures, its read-out noise removed, and beyond the
    log its forecast (what the channel terms of the physics model respond to).
    """

    channel_t_s: list[float] = field(default_factory=list)
    channels: dict[str, list[float]] = field(default_factory=dict)
    events: list[Event] = field(default_factory=list)
    # Arrays of (log length, finite times, finite values) per channel, rebuilt
    # when the log grows: channel_at is called many times per frame.
    _arrays: dict[str, tuple[int, npt.NDArray[np.float64], npt.NDArray[np.float64]]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )
    # Per channel: (log length, the log with its read-out noise removed).
    _sensed: dict[str, tuple[int, SmoothedChannel]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )
    # Per event kind: (log state, times, (n, 2) x/y) for the design matrices of
    # event terms, which a fit builds dozens of times per frame (a closed loop
    # logs thousands of offset moves).
    _kinds: dict[str, tuple[int, npt.NDArray[np.float64], npt.NDArray[np.float64]]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def add_channels(self, sample: ChannelSample) -> None:
        if self.channel_t_s and sample.t_s < self.channel_t_s[-1]:
            raise ValueError(
                f"channel sample at t={sample.t_s} s is older than the last "
                f"({self.channel_t_s[-1]} s)"
            )
        n = len(self.channel_t_s)
        self.channel_t_s.append(float(sample.t_s))
        for name, value in sample.values.items():
            col = self.channels.setdefault(name, [float("nan")] * n)
            col.append(float(value))
        for col in self.channels.values():
            if len(col) < n + 1:
                col.append(float("nan"))

    def add_events(self, events: Iterable[Event]) -> None:
        for e in events:
            bisect.insort(self.events, e, key=lambda ev: ev.t_s)

    def of_kind(
        self, kind: EventKind | str
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Times (n,) and ``(x_nm, y_nm)`` (n, 2) of the events of ``kind``, in time order."""
        key = len(self.events)  # the log only grows
        name = str(kind)
        cached = self._kinds.get(name)
        if cached is None or cached[0] != key:
            t, xy = events_of_kind(self.events, kind)
            cached = self._kinds[name] = (key, t, xy)
        return cached[1], cached[2]

    def channel_at(self, name: str, t_s: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Channel ``name`` at ``t_s`` (linear inside the log, held outside)."""
        if name not in self.channels:
            raise KeyError(f"no channel {name!r} logged (have: {sorted(self.channels)})")
        n = len(self.channel_t_s)
        cached = self._arrays.get(name)
        if cached is None or cached[0] != n:
            t = np.asarray(self.channel_t_s, dtype=np.float64)
            v = np.asarray(self.channels[name], dtype=np.float64)
            ok = np.isfinite(v)
            cached = (n, t[ok], v[ok])
            self._arrays[name] = cached
        _, tk, vk = cached
        if tk.size == 0:
            return np.full(np.shape(t_s), np.nan)
        return np.interp(np.asarray(t_s, dtype=np.float64), tk, vk)

    def sensed(self, name: str) -> SmoothedChannel:
        """Channel ``name`` with its read-out noise removed, at its finite samples.

        The state-space cubic smoothing spline of :mod:`afmdrift.model._denoise`
        (signal-to-noise ratio by maximum likelihood) over everything logged so
        far; recomputed when the log grows.
        """
        if name not in self.channels:
            raise KeyError(f"no channel {name!r} logged (have: {sorted(self.channels)})")
        n = len(self.channel_t_s)
        cached = self._sensed.get(name)
        if cached is None or cached[0] != n:
            cached = (n, smooth_channel(self.channel_t_s, self.channels[name]))
            self._sensed[name] = cached
        return cached[1]

    def sensed_at(self, name: str, t_s: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """:meth:`sensed` at ``t_s``: linear inside the log, held before it,
        forecast along the quantity's slope at the last sample after it."""
        return self.sensed(name).at(t_s)

    def events_before(self, t_s: float) -> Sequence[Event]:
        k = bisect.bisect_right(self.events, t_s, key=lambda ev: ev.t_s)
        return self.events[:k]


@dataclass(frozen=True, slots=True)
class Prediction:
    """Predicted drift at one or more times.

    ``t_s`` has shape (n,); ``mean_nm`` and ``sigma_nm`` have shape (n, 2) for (x, y).
    """

    t_s: npt.NDArray[np.float64]
    mean_nm: npt.NDArray[np.float64]
    sigma_nm: npt.NDArray[np.float64]


class Predictor(abc.ABC):
    """Common interface of every drift predictor.

    Lifecycle: ``update`` once per new frame (in time order), ``predict`` any
    number of times, ``state_dict``/``load_state_dict`` to survive restarts.
    Implementations must be deterministic for a given seed.
    """

    #: Name used on the command line and in configuration (``--predictors``).
    name: ClassVar[str]

    @abc.abstractmethod
    def update(self, obs: Observation, history: History) -> None:
        """Incorporate a new measurement; ``history`` holds channels and events up to now."""

    @abc.abstractmethod
    def predict(self, t_s: npt.ArrayLike, history: History) -> Prediction:
        """Predict p at times ``t_s`` (usually after the last observation)."""

    @abc.abstractmethod
    def state_dict(self) -> dict[str, Any]:
        """JSON-serialisable state (arrays as lists) from which the model resumes."""

    @abc.abstractmethod
    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the state produced by :meth:`state_dict`."""

    def predict_observation(
        self, obs: Observation, history: History
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """What ``obs`` is predicted to measure: mean (2,) and σ (2,).

        The mean of :meth:`predict` over the measurement's scan window
        (:meth:`Observation.samples`), σ the mean of the σ there (an upper
        bound of the σ of the mean). The one-step error of every predictor is
        scored against this, in the service and in ``evaluate``.
        """
        pred = self.predict_scanned(obs.samples(), obs.direction, history)
        mean = np.asarray(pred.mean_nm, dtype=np.float64).reshape(-1, 2).mean(axis=0)
        sigma = np.asarray(pred.sigma_nm, dtype=np.float64).reshape(-1, 2).mean(axis=0)
        return mean, sigma

    def predict_scanned(
        self, t_s: npt.ArrayLike, direction: ScanDirection, history: History
    ) -> Prediction:
        """:meth:`predict` at ``t_s`` for a frame scanned in ``direction``
        (known once it is scanned); the default ignores the direction."""
        return self.predict(t_s, history)

    def predict_drift(self, t_s: npt.ArrayLike, history: History) -> Prediction:
        """Predict the sample position itself, without measurement artefacts.

        :meth:`predict` says what the next frame will measure (scored against
        measurements); this is what the tip should follow (used for d(t)). They
        differ only for models that know a measurement artefact such as the
        up/down scan bias; the default returns :meth:`predict`.
        """
        return self.predict(t_s, history)

    def offset_play(self) -> OffsetPlay | None:
        """The play hysteresis of offset moves this model has fitted, for a
        closed loop to pre-compensate its own moves (None: not modelled)."""
        return None

    def observed(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Times (n,) and positions (n, 2) of the observations seen so far.

        Used by the reconstruction (the sinc formula sums over measured
        samples). The default says "none"; every built-in predictor overrides it.
        """
        return np.zeros(0), np.zeros((0, 2))
