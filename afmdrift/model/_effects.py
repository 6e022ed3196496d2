"""A library of physical drift effects, each a small parametric term.

Every term contributes, per axis, a few *basis functions* of time built from
the logged channels and events, given the term's *nonlinear parameters*
(time constants). The drift model is linear in the basis coefficients::

    p_axis(t) = Σ_terms  B_term(t; θ_term, axis) · β_term,axis

so fitting is a weighted least-squares solve for β once the θ are fixed, and a
1-D scan plus bounded refinement over each θ (see
:class:`afmdrift.model.PhysicsPredictor`). This split is also what the
diagnostics use: for any library term not in the model they call
:meth:`EffectTerm.design` on the residual times for every candidate in
:meth:`EffectTerm.nonlinear_grid` and test the added variables.

Term API
--------
``design(t_s, history, *, scan_sign, params, axis) -> (n, k)``
    Basis matrix at times ``t_s`` for one axis (0 = x, 1 = y). ``scan_sign``
    is +1 for up frames and −1 for down frames at those times. ``params``
    maps every name of :attr:`EffectTerm.nonlinear_params` to a value. Columns
    that are zero everywhere carry no information and are dropped by the fit.
``nonlinear_grid()``
    Candidate nonlinear parameter sets (log-spaced inside the bounds).
``missing(history)``
    Why the term cannot be built from this history (a channel not logged), or
    ``None``.

Users add terms without editing afmdrift: subclass :class:`EffectTerm`, give
it a unique ``name`` and register it under the entry-point group
``afmdrift.effects`` or list ``"package.module:Class"`` in
``[model.physics] plugins`` (see ``docs/effects-plugins.md``); terms are
found by name in :mod:`afmdrift.model._terms`.
"""

from __future__ import annotations

import abc
import functools
import itertools
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numba
import numpy as np
import numpy.typing as npt

from afmdrift.model._base import History
from afmdrift.records import EventKind

__all__ = [
    "LIBRARY",
    "EffectTerm",
    "LaggedChannel",
    "NonlinearParam",
    "offset_through_play",
    "play_gaps",
    "step_through_play",
    "windowed_design",
]


FloatArray = npt.NDArray[np.float64]

#: Search range of ``tau_s`` of a response to a logged channel (``thermal_lag``
#: and the generic ``channel:`` terms), s; the lower end is no lag, so a lagged
#: term also describes a direct response.
CHANNEL_TAU_RANGE_S = (1.0, 20000.0)


@dataclass(frozen=True, slots=True)
class NonlinearParam:
    """A nonlinear parameter of a term, searched on a bounded log scale.

    Attributes
    ----------
    name : str
        Key in the ``params`` mapping (with its unit, e.g. ``tau_s``).
    lower, upper : float
        Search bounds (positive).
    default : float
        Value used before any fit.
    grid_points : int
        Number of log-spaced candidates in :meth:`EffectTerm.nonlinear_grid`.
    """

    name: str
    lower: float
    upper: float
    default: float
    grid_points: int = 13

    def grid(self) -> FloatArray:
        return np.geomspace(self.lower, self.upper, self.grid_points)


class EffectTerm(abc.ABC):
    """One physical effect: basis functions given nonlinear parameters.

    Subclasses set :attr:`name`, :attr:`nonlinear_params` (may be empty),
    :attr:`provides_intercept` if a basis column is constant, and implement
    :meth:`design`. Their docstring gives the equation and the meaning and
    unit of each coefficient.
    """

    #: Canonical name used in ``[model.physics] terms``.
    name: ClassVar[str]
    #: Nonlinear parameters, searched by the fit.
    nonlinear_params: ClassVar[tuple[NonlinearParam, ...]] = ()
    #: True if one basis column is the constant 1 (the model then adds no intercept).
    provides_intercept: ClassVar[bool] = False
    #: Fitted points on which a basis column must be non-zero before its
    #: coefficient is fitted (else it is held at 0).
    min_column_support: ClassVar[int] = 1
    #: Names of the linear coefficients with units, for reports.
    coefficient_units: ClassVar[tuple[str, ...]] = ()
    #: True if the term describes how frames measure the position (not where the
    #: sample is): it is fitted, but left out of the offset d(t) the tip follows.
    measurement_artefact: ClassVar[bool] = False

    @abc.abstractmethod
    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        """Basis matrix, shape (n, k), at times ``t_s`` (shape (n,)) for ``axis``."""

    def missing(self, history: History) -> str | None:
        """Reason this term cannot be built from ``history``, or ``None``."""
        return None

    def default_params(self) -> dict[str, float]:
        return {p.name: p.default for p in self.nonlinear_params}

    def nonlinear_grid(self) -> list[dict[str, float]]:
        """Candidate nonlinear parameter sets (the Cartesian product of each grid)."""
        if not self.nonlinear_params:
            return [{}]
        grids = [p.grid() for p in self.nonlinear_params]
        names = [p.name for p in self.nonlinear_params]
        return [
            {n: float(v) for n, v in zip(names, combo, strict=True)}
            for combo in itertools.product(*grids)
        ]


def windowed_design(
    term: EffectTerm,
    times: FloatArray,
    history: History,
    *,
    scan_sign: FloatArray,
    params: Mapping[str, float],
    axis: int,
) -> FloatArray:
    """``term``'s basis for measurements that average over their scan windows.

    ``times`` is (n,) for point measurements or (n, m) sample times per
    measurement (:func:`~afmdrift.model._base.scan_samples`); a row's basis is
    the mean of :meth:`EffectTerm.design` over its m samples, so a frame is
    described by the mean of p over the lines it scanned. Every model fit and
    every diagnose candidate builds its columns here.
    """
    t = np.asarray(times, dtype=np.float64)
    sign = np.asarray(scan_sign, dtype=np.float64)
    if t.ndim == 1 or t.shape[1] == 1:
        return term.design(t.reshape(-1), history, scan_sign=sign, params=params, axis=axis)
    n, m = t.shape
    block = term.design(
        t.reshape(-1), history, scan_sign=np.repeat(sign, m), params=params, axis=axis
    )
    return np.asarray(block.reshape(n, m, -1).mean(axis=1), dtype=np.float64)


def _channel_missing(history: History, name: str) -> str | None:
    if name not in history.channels:
        return f"channel {name!r} is not logged (have: {sorted(history.channels)})"
    if not np.isfinite(np.asarray(history.channels[name], dtype=np.float64)).any():
        return f"channel {name!r} has no finite values"
    return None


def _first_finite(history: History, name: str) -> float:
    v = np.asarray(history.channels[name], dtype=np.float64)
    return float(v[np.isfinite(v)][0])


class Trend(EffectTerm):
    """Constant drift velocity plus an offset.

    p(t) = a + v·t/3600, with a the offset (nm) and v the velocity (nm/h),
    t on the instrument clock. The generic slow drift that every model needs.
    """

    name = "trend"
    provides_intercept = True
    coefficient_units = ("offset_nm", "velocity_nm_per_h")

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        return np.column_stack([np.ones_like(t_s), t_s / 3600.0])


class _ChannelProportional(EffectTerm):
    """p(t) = k·(C(t) − C₀) for a logged channel C (C₀ its first logged value).

    C is the quantity the sensor measures, its read-out noise removed
    (:meth:`History.sensed_at`): the drift follows the quantity, not the noise.
    """

    channel: ClassVar[str]

    def missing(self, history: History) -> str | None:
        return _channel_missing(history, self.channel)

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        v = history.sensed_at(self.channel, t_s) - _first_finite(history, self.channel)
        return v[:, None]


class Thermal(_ChannelProportional):
    """Thermal expansion proportional to the logged temperature.

    p(t) = k·(T(t) − T₀), T the logged ``temperature_c`` (read through its
    noise and forecast beyond the log, :meth:`History.sensed_at`), T₀ its
    first logged value, k in nm/K: the expansion coefficient times the
    thermal path length of the sample-scanner loop.
    """

    name = "thermal"
    coefficient_units = ("k_nm_per_K",)
    channel = "temperature_c"


class Humidity(_ChannelProportional):
    """Hygroscopic swelling proportional to the logged relative humidity.

    p(t) = k·(RH(t) − RH₀), RH the logged ``humidity_pct``, RH₀ its first
    logged value, k in nm/%RH.
    """

    name = "humidity"
    coefficient_units = ("k_nm_per_pct_rh",)
    channel = "humidity_pct"


class LaggedChannel(EffectTerm):
    """Response to a logged channel through a first-order lag (shared code).

    The driven quantity C_s follows the channel C through a first-order
    low-pass, τ·dC_s/dt = C − C_s, with C_s(t₀) = C(t₀) at the first log
    entry; p(t) = k·(C_s(t) − C₀), C₀ the first logged value. C is the
    logged channel with its read-out noise removed
    (:meth:`History.sensed_at`). Beyond the log, C is its forecast, a ramp
    along the last slope, and C_s follows the ramp through the lag. A τ at or
    below :attr:`no_lag_s` is no lag at all (p = k·(C − C₀)). Subclasses set :attr:`channel` and the
    ``tau_s`` search range.
    """

    channel: ClassVar[str]
    #: τ (s) at or below which the response is taken as direct (τ = 0).
    no_lag_s: ClassVar[float] = 0.0

    def __init__(self) -> None:
        self._cache: dict[tuple[float, int], tuple[FloatArray, FloatArray]] = {}
        self._grid: tuple[int, FloatArray, FloatArray] | None = None

    def missing(self, history: History) -> str | None:
        return _channel_missing(history, self.channel)

    def lagged(self, t_s: FloatArray, history: History, tau_s: float) -> FloatArray:
        """Low-passed channel C_s(t) − C₀ at ``t_s`` (channel units)."""
        if tau_s <= self.no_lag_s:
            return np.asarray(
                history.sensed_at(self.channel, t_s) - _first_finite(history, self.channel),
                dtype=np.float64,
            )
        tg, yg = self._filtered(history, tau_s)
        out = np.interp(t_s, tg, yg)
        beyond = t_s > tg[-1]
        if beyond.any():
            # The lag of the ramp C = c + s·u (u the time after the grid's end)
            # from C_s = y there: C_s = c + s·(u − τ) + (y − c + s·τ)·exp(−u/τ).
            c = float(self._resampled(history)[1][-1])
            slope = history.sensed(self.channel).slope_per_s
            u = t_s[beyond] - tg[-1]
            decay = np.exp(-u / tau_s)
            out[beyond] = c + slope * (u - tau_s) + (yg[-1] - c + slope * tau_s) * decay
        return out

    def _resampled(self, history: History) -> tuple[FloatArray, FloatArray]:
        """Channel (read-out noise removed) − C₀ on a uniform grid (cached per log length)."""
        key = len(history.channel_t_s)
        if self._grid is not None and self._grid[0] == key:
            return self._grid[1], self._grid[2]
        t = np.asarray(history.channel_t_s, dtype=np.float64)
        span = float(t[-1] - t[0]) if t.size > 1 else 0.0
        if span <= 0:
            grid = np.array([t[0], t[0] + 1.0])
        else:
            # At most 20000 points; the smallest τ searched spans many of them.
            step = max(span / 20000.0, float(np.median(np.diff(t))))
            grid = np.arange(t[0], t[-1] + 0.5 * step, step)
        values = history.sensed_at(self.channel, grid) - _first_finite(history, self.channel)
        self._grid = (key, grid, values)
        self._cache.clear()
        return grid, values

    def _filtered(self, history: History, tau_s: float) -> tuple[FloatArray, FloatArray]:
        grid, values = self._resampled(history)
        key = (float(tau_s), len(history.channel_t_s))
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        h = float(grid[1] - grid[0])
        a = np.exp(-h / tau_s)
        result = (grid, _first_order_lag(np.asarray(values, dtype=np.float64), float(a)))
        if len(self._cache) > 64:
            self._cache.clear()
        self._cache[key] = result
        return result

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        return self.lagged(t_s, history, float(params["tau_s"]))[:, None]


class ThermalLag(LaggedChannel):
    """Thermal expansion of a scanner whose temperature lags the logged one.

    The scanner temperature T_s follows the logged temperature T through a
    first-order low-pass, τ·dT_s/dt = T − T_s, with T_s(t₀) = T(t₀) at the
    first log entry; p(t) = k·(T_s(t) − T₀). Parameters: k in nm/K (as for
    ``thermal``) and the thermal time constant ``tau_s`` in s (how long the
    scanner takes to follow the room or stage sensor); τ ≤ 1 s is no lag, so
    the term holds ``thermal`` as its limit. Beyond the log, T is its
    forecast along the last slope (:meth:`History.sensed_at`), and T_s
    follows it through the lag.
    """

    name = "thermal_lag"
    nonlinear_params = (NonlinearParam("tau_s", *CHANNEL_TAU_RANGE_S, 1200.0, grid_points=25),)
    no_lag_s = CHANNEL_TAU_RANGE_S[0]
    coefficient_units = ("k_nm_per_K",)
    channel = "temperature_c"


def _moves(history: History, axis: int) -> tuple[FloatArray, FloatArray]:
    t, d = history.of_kind(EventKind.OFFSET_MOVE)
    return t, d[:, axis]


# A closed loop logs a move every few seconds (thousands per session), and each
# design is called dozens of times per fit: beyond this many (times × moves)
# the creep sum takes far moves by bins.
_CREEP_DIRECT = 1 << 15
_CREEP_NEAR_BINS = 4  # bins before t whose moves are summed one by one
_LN10 = float(np.log(10.0))


def log_creep_sum(
    t_s: FloatArray, t_moves: FloatArray, steps: FloatArray, t0_s: float
) -> FloatArray:
    """Σ_m Δ_m · log10(1 + max(t − t_m, 0)/t₀) at each t (moves sorted by time).

    Exact for up to :data:`_CREEP_DIRECT` (times × moves). Beyond, the n
    moves are put in B = √(5n) bins (16 to 256) of width w over their span
    (cost ∝ times × (B + 5n/B)); those of the last :data:`_CREEP_NEAR_BINS`
    + 1 bins before t are summed one by one, older bins through the
    second-order Taylor expansion of the kernel about the bin centre c
    (moments Σ Δ, Σ Δ(t_m − c), Σ Δ(t_m − c)²). With u = t − c ≥ 4.5w the
    third-order remainder is below 3·10⁻⁴ of Σ|Δ| per bin (the kernel's
    scale there is t₀ + u ≥ 4.5w whatever t₀).
    """
    t_s = np.asarray(t_s, dtype=np.float64)
    out = np.zeros(t_s.shape, dtype=np.float64)
    if t_moves.size == 0 or t_s.size == 0:
        return out
    if t_moves.size * t_s.size <= _CREEP_DIRECT:
        dt = np.maximum(t_s[:, None] - t_moves[None, :], 0.0)
        return np.log10(1.0 + dt / t0_s) @ steps
    start = float(t_moves[0])
    bins = int(np.clip(np.sqrt((_CREEP_NEAR_BINS + 1) * t_moves.size), 16, 256))
    w = max(float(t_moves[-1] - start) / bins, 1e-6)
    b = np.minimum(((t_moves - start) / w).astype(np.int64), bins - 1)
    nb = int(b[-1]) + 1
    centre = start + (np.arange(nb) + 0.5) * w
    off = t_moves - centre[b]
    m0 = np.bincount(b, steps, nb)
    m1 = np.bincount(b, steps * off, nb)
    m2 = np.bincount(b, steps * off * off, nb)
    # Bins up to far_last[i] are far from t_i; later moves before t_i are near.
    far_last = np.floor((t_s - start) / w).astype(np.int64) - _CREEP_NEAR_BINS - 1
    far = np.arange(nb)[None, :] <= far_last[:, None]
    if far.any():
        a = t0_s + np.where(far, t_s[:, None] - centre[None, :], 0.0)
        taylor = m0 * np.log10(a / t0_s) - m1 / (_LN10 * a) - 0.5 * m2 / (_LN10 * a * a)
        out += np.sum(np.where(far, taylor, 0.0), axis=1)
    lo = np.searchsorted(b, far_last + 1, side="left")
    hi = np.searchsorted(t_moves, t_s, side="left")
    n_near = np.maximum(hi - lo, 0)
    width = int(n_near.max(initial=0))
    if width:
        k = np.arange(width)[None, :]
        idx = np.minimum(lo[:, None] + k, t_moves.size - 1)
        dt = np.maximum(t_s[:, None] - t_moves[idx], 0.0)
        near = np.where(k < n_near[:, None], steps[idx] * np.log10(1.0 + dt / t0_s), 0.0)
        out += near.sum(axis=1)
    return out


class Creep(EffectTerm):
    """Logarithmic piezo creep after each commanded offset move.

    p(t) = c · Σ_m Δ_m · log10(1 + (t − t_m)/t₀) for t > t_m, summed over the
    logged ``offset_move`` events m with step Δ_m on this axis. c is the
    dimensionless creep fraction per decade of time (typically 0.01–0.2) and
    ``t0_s`` the creep onset time scale in s.
    """

    name = "creep"
    nonlinear_params = (NonlinearParam("t0_s", 0.3, 3000.0, 10.0, grid_points=13),)
    coefficient_units = ("c_per_decade",)

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        tm, dm = _moves(history, axis)
        keep = dm != 0.0
        return log_creep_sum(t_s, tm[keep], dm[keep], float(params["t0_s"]))[:, None]


class Warmup(EffectTerm):
    """Exponential thermal settling after power-on.

    p(t) = A·(1 − exp(−(t − t_on)/τ_w)) for t > t_on, t_on the most recent
    logged ``power_on`` event before t. A (nm) is the total warm-up excursion,
    ``tau_w_s`` (s) the settling time constant.
    """

    name = "warmup"
    nonlinear_params = (NonlinearParam("tau_w_s", 120.0, 40000.0, 3600.0, grid_points=15),)
    coefficient_units = ("amplitude_nm",)

    def missing(self, history: History) -> str | None:
        if not history.of_kind(EventKind.POWER_ON)[0].size:
            return "no power_on event logged"
        return None

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        return _settling(t_s, history, float(params["tau_w_s"]))[:, None]


def _settling(t_s: FloatArray, history: History, tau_s: float) -> FloatArray:
    """1 − exp(−(t − t_on)/τ) after the most recent ``power_on`` before t, else 0."""
    on = history.of_kind(EventKind.POWER_ON)[0]
    out = np.zeros_like(t_s)
    if on.size == 0:
        return out
    k = np.searchsorted(on, t_s, side="right") - 1
    ok = k >= 0
    out[ok] = 1.0 - np.exp(-(t_s[ok] - on[k[ok]]) / tau_s)
    return out


class WarmupTwo(EffectTerm):
    """Thermal settling after power-on along a fast and a slow path.

    p(t) = A₁·(1 − exp(−Δt/τ₁)) + A₂·(1 − exp(−Δt/τ₂)), Δt = t − t_on since the
    most recent logged ``power_on``: the scanner tube settles within tens of
    minutes (τ₁ ``tau_fast_s``, 120–3600 s), the stage and frame over hours
    (τ₂ ``tau_slow_s``, 3600–40000 s); A₁, A₂ (nm) their excursions. A warm-up
    that does not follow one exponential is named by this term; where one
    exponential is enough, ``warmup`` (fewer parameters) is preferred.
    """

    name = "warmup_two"
    nonlinear_params = (
        NonlinearParam("tau_fast_s", 120.0, 3600.0, 1200.0, grid_points=10),
        NonlinearParam("tau_slow_s", 3600.0, 40000.0, 9000.0, grid_points=10),
    )
    coefficient_units = ("amplitude_fast_nm", "amplitude_slow_nm")

    def missing(self, history: History) -> str | None:
        return Warmup().missing(history)

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        return np.column_stack(
            [
                _settling(t_s, history, float(params["tau_fast_s"])),
                _settling(t_s, history, float(params["tau_slow_s"])),
            ]
        )


class ScanDirectionBias(EffectTerm):
    """Apparent offset between up- and down-scanned frames.

    p(t) = b·s/2, s = +1 for up frames and −1 for down frames: b (nm) is the
    up-minus-down bias of the measured position, caused by slow-axis creep and
    hysteresis of the scanner during the frame.
    """

    name = "scan_direction"
    coefficient_units = ("bias_nm",)
    measurement_artefact = True

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        return (0.5 * np.asarray(scan_sign, dtype=np.float64))[:, None]


@numba.njit(cache=True, nogil=True)
def _first_order_lag(values: FloatArray, a: float) -> FloatArray:  # pragma: no cover
    """First-order lag of evenly sampled ``values`` with pole ``a``:
    ``y[n] = (1 − a)·x[n] + a·y[n − 1]``, started in equilibrium with the
    first sample (``y[−1] = x[0]``). Compiled here rather than through
    ``scipy.signal.lfilter``, whose import alone took 0.8 s of every command
    that loads the model."""
    out = np.empty(values.size)
    b = 1.0 - a
    if values.size == 0:
        return out
    state = a * values[0]
    for n in range(values.size):
        y = b * values[n] + state
        out[n] = y
        state = a * y
    return out


@numba.njit(cache=True, nogil=True)
def _play_gaps(steps: FloatArray, r: float, gap0: float) -> FloatArray:  # pragma: no cover
    out = np.empty(steps.size)
    g = gap0
    for k in range(steps.size):
        # the commanded offset moves by steps[k]; the scanner y stays put while
        # |c − y| ≤ r, else it is dragged along: g = y − c stays in [−r, r]
        g = min(max(g - steps[k], -r), r)
        out[k] = g
    return out


@functools.cache
def warm_up_effects() -> None:
    """Compile (or load from Numba's disk cache) the effect terms' kernels
    once per process: the physics model does it when it is made and the
    daemon at its start, so no compile holds the GIL in the middle of a run
    (0.2 s from the cache, 0.7 s after an install)."""
    _first_order_lag(np.zeros(2), 0.5)
    _play_gaps(np.zeros(2), 1.0, 0.0)


def play_gaps(steps: npt.ArrayLike, play_nm: float, gap0_nm: float = 0.0) -> FloatArray:
    """Gap g = y − c between the scanner y and the commanded offset c after
    each of ``steps`` (one axis), for a play (backlash) of half-width
    ``play_nm`` that starts with gap ``gap0_nm``: ``g_k = clip(g_{k−1} − Δ_k, −r, r)``.
    """
    return np.asarray(
        _play_gaps(np.ascontiguousarray(steps, dtype=np.float64), float(play_nm), float(gap0_nm)),
        dtype=np.float64,
    )


def step_through_play(want_nm: float, gap_nm: float, play_nm: float, gain: float) -> float:
    """The commanded step Δ (one axis) that moves the image content by
    ``want_nm``, counting the change of the play gap it causes.

    A step Δ moves the content by ``Δ − gain·(g' − g)`` with
    ``g' = clip(g − Δ, −r, r)`` (:func:`play_gaps`); for gain ≥ −1 that is
    non-decreasing in Δ and piecewise linear, so it inverts in closed form:
    inside the play a step moves the content by ``(1 + gain)·Δ``, beyond it by
    ``Δ + gain·(r ± g)``. Gain −1 is a scanner that lags its command by the
    play (a step inside it moves nothing): the step then takes up the play and
    goes on by ``want_nm``.
    """
    r, k, g = float(play_nm), float(gain), float(gap_nm)
    if k < -1.0:
        raise ValueError(
            f"play gain {k} must be >= -1 (the content would move against the command)"
        )
    if want_nm == 0.0:
        return 0.0
    if want_nm >= (g + r) * (1.0 + k):
        return float(want_nm - k * (r + g))
    if want_nm <= (g - r) * (1.0 + k):
        return float(want_nm + k * (r - g))
    return float(want_nm / (1.0 + k))


def offset_through_play(
    want_nm: float, *, sent: float, gap_nm: float, gap_seen_nm: float, play_nm: float, gain: float
) -> float:
    """The absolute offset to command (one axis) so the image lands where
    ``want_nm`` would put it without the play.

    ``want_nm`` is the hold position plus d(t), and d(t) holds ``gain`` times
    the gap after the moves the model has seen (``gap_seen_nm``). ``sent`` is
    the last offset commanded and ``gap_nm`` the gap after it. The step from
    ``sent`` moves the content by what d(t) asks, plus what the gap changed
    since the model's moves, through :func:`step_through_play`.
    """
    if gain == 0.0:
        return float(want_nm)
    move = want_nm - sent + gain * (gap_nm - gap_seen_nm)
    return float(sent + step_through_play(move, gap_nm, play_nm, gain))


class Hysteresis(EffectTerm):
    """Positioning error of offset moves: a play (backlash) operator.

    The scanner follows the commanded offset c (the sum of the logged
    ``offset_move`` steps on this axis) with a play of half-width r: after
    each move y = clip(y_prev, c − r, c + r), so the gap g = y − c stays in
    [−r, r] (one Prandtl–Ishlinskii play operator, the elementary model of
    piezo hysteresis, as in the simulator: docs/physics.md).

    p(t) = h·s(t), s = −g/r ∈ [−1, 1] after the latest move before t (0
    before any). A move of more than 2r gives s = sign of that move, so h (nm)
    is half the hysteresis gap between approaching a position from below and
    from above; small moves back and forth (a closed loop holding a spot)
    travel through the play and move s gradually. r (nm, ``play_nm``) is
    fitted; below the smallest move it is the sign of the last move.
    """

    name = "hysteresis"
    coefficient_units = ("h_nm",)
    nonlinear_params = (NonlinearParam("play_nm", 0.05, 10.0, 1.0, grid_points=12),)

    def missing(self, history: History) -> str | None:
        if not history.of_kind(EventKind.OFFSET_MOVE)[0].size:
            return "no offset_move event logged"
        return None

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        tm, dm = _moves(history, axis)
        out = np.zeros_like(t_s)
        if tm.size:
            r = float(params["play_nm"])
            s = -play_gaps(dm, r) / r
            k = np.searchsorted(tm, t_s, side="right") - 1
            ok = k >= 0
            out[ok] = s[k[ok]]
        return out[:, None]


class TipChange(EffectTerm):
    """A position step at each logged tip change.

    p(t) = Σ_j s_j·H(t − t_j), one column per logged ``tip_change`` event j;
    s_j (nm) is the apparent jump of the image when the imaging apex changes.
    """

    name = "tip_change"
    coefficient_units = ("step_nm",)

    def missing(self, history: History) -> str | None:
        if not history.of_kind(EventKind.TIP_CHANGE)[0].size:
            return "no tip_change event logged"
        return None

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        tc = history.of_kind(EventKind.TIP_CHANGE)[0]
        if not tc.size:
            return np.zeros((t_s.size, 0))
        return np.column_stack([(t_s > t).astype(np.float64) for t in tc])


#: The canonical library, by name.
LIBRARY: dict[str, type[EffectTerm]] = {
    cls.name: cls
    for cls in (
        Trend,
        Thermal,
        ThermalLag,
        Humidity,
        Creep,
        Warmup,
        WarmupTwo,
        ScanDirectionBias,
        Hysteresis,
        TipChange,
    )
}
