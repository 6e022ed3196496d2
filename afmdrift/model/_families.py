"""Generic term families: the response to any logged channel or event kind.

The library (:mod:`afmdrift.model._effects`) names the effects afmdrift knows
(thermal lag, creep, warm-up, ...). A real instrument also drifts with things
no library term is called: barometric pressure, a second thermometer on the
stage, laser power, a door, a tip approach. Two families cover them, each
instance written as a **term spec**, a string accepted wherever a term name is
(``[model.physics] terms``, ``--effects``)::

    channel:<channel>[:<option>...][#<label>]
    event:<kind>[:<option>...][#<label>]

``channel:<channel>``
    p(t) = g·(C_s(t) − C₀): the logged channel C (a column of
    ``channels.csv``) through a first-order lag τ·dC_s/dt = C − C_s, C₀ its
    first logged value. g (``gain_nm_per_<unit>``, the unit taken from the
    channel name's suffix, e.g. ``gain_nm_per_hpa`` for ``pressure_hpa``) per
    axis; τ (``tau_s``) scanned on a log grid from 1 s to 20000 s, where
    τ ≤ 1 s is computed as no lag (τ = 0): a direct, proportional response.
``event:<kind>`` (shape ``settle``, the default)
    p(t) = A·Σ_j (1 − exp(−(t − t_j)/τ)) over the logged events j of that
    kind: a step of A (``amplitude_nm``) per event that settles exponentially
    with τ (``tau_s``, 30–20000 s).
``event:<kind>:log``
    p(t) = c·Σ_j log10(1 + (t − t_j)/t₀): logarithmic creep after each event,
    c (``nm_per_decade``), t₀ (``t0_s``, 0.3–3000 s).

Options:

* ``each`` (events): one amplitude per event instead of one shared by all
  events of the kind (``event:stage_move:each``), for events whose response
  differs in size or direction.
* ``tau_s=<lo>..<hi>`` or ``t0_s=<lo>..<hi>``: search range of the time
  constant (s); ``tau_s=<value>`` fixes it (no search).
* ``#<label>`` (lower-case letters, digits, ``_``): a second instance of the
  same driver, e.g. a fast and a slow
  thermal path ``channel:stage_c:tau_s=1..600#fast`` and
  ``channel:stage_c:tau_s=600..20000#slow``. Two identical specs in one model
  are rejected as duplicates.

Three more families describe a shape of the drift itself, at a time or a
period that ``afmdrift diagnose`` reads from the drift when nothing logged
explains it (times in s from the session's start, on the clock of
``positions.csv``)::

    periodic:period_s=<P>[#<label>]
    jump:t_s=<t>[#<label>]
    rate_change:t_s=<t>[#<label>]

``periodic:period_s=<P>``
    p(t) = a·sin(2πt/P) + b·cos(2πt/P): a cycle of period P (an air handler,
    a thermostat); a and b (``sin_nm``, ``cos_nm``) per axis, so amplitude
    and phase are fitted.
``jump:t_s=<t>``
    p(t) = A·H(t − t_j): a step of A (``step_nm``) at t_j (a slip, a tip
    change); H is 0 before and 1 after.
``rate_change:t_s=<t>``
    p(t) = r·max(0, t − t_k)/3600: the drift rate changes by r
    (``rate_change_nm_per_h``) at t_k (a door closed, a chiller switched).

The value may also be a range ``<lo>..<hi>``, searched like a time constant.

A spec's term name is the spec itself. Errors name the spec and the offending
part (:class:`~afmdrift.errors.ConfigError`).
"""

from __future__ import annotations

import abc
import functools
import math
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from afmdrift.errors import ConfigError
from afmdrift.model._base import History
from afmdrift.model._effects import (
    CHANNEL_TAU_RANGE_S,
    EffectTerm,
    LaggedChannel,
    NonlinearParam,
)
from afmdrift.records import event_kind

__all__ = [
    "CHANNEL_TAU_RANGE_S",
    "ChannelResponse",
    "DriftShape",
    "EventResponse",
    "GenericTerm",
    "is_term_spec",
    "parse_term_spec",
]

FloatArray = npt.NDArray[np.float64]

#: Default ``tau_s`` range of the ``settle`` event response, s.
SETTLE_TAU_RANGE_S = (30.0, 20000.0)
#: Default ``t0_s`` range of the ``log`` event response, s.
LOG_T0_RANGE_S = (0.3, 3000.0)

_SHAPES = ("settle", "log")
_NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyz0123456789_")


class GenericTerm(EffectTerm):
    """Base of the generic families: the driver of a term, for reports."""

    #: Fixed values of nonlinear parameters given in the spec (not searched).
    fixed_params: ClassVar[Mapping[str, float]] = {}

    @abc.abstractmethod
    def driver(self) -> dict[str, str]:
        """What drives the term: ``{"channel": name}`` or ``{"event_kind": ..., "shape": ...}``."""

    def _params(self, params: Mapping[str, float]) -> dict[str, float]:
        return {**self.fixed_params, **params}

    def __reduce__(self) -> tuple[Any, ...]:
        # Its class is built from the spec at run time (parse_term_spec), so
        # pickle cannot find it by name: a term travels as its spec and state
        # (to the processes of diagnose's online re-runs, to Dask workers).
        return (_term_from_spec, (self.name, dict(vars(self))))


class ChannelResponse(GenericTerm, LaggedChannel):
    """Response to a logged channel, proportional through a first-order lag.

    p(t) = g·(C_s(t) − C₀), τ·dC_s/dt = C − C_s (see
    :class:`afmdrift.model.LaggedChannel`); τ ≤ 1 s is no lag. g in nm per
    channel unit, τ (``tau_s``) in s.
    """

    no_lag_s = CHANNEL_TAU_RANGE_S[0]

    def driver(self) -> dict[str, str]:
        return {"channel": self.channel}

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        return self.lagged(t_s, history, float(self._params(params)["tau_s"]))[:, None]


class EventResponse(GenericTerm):
    """Response to each logged event of one kind: exponential settling or log creep.

    ``settle``: A·(1 − exp(−(t − t_j)/τ)) after each event j, A in nm, τ
    (``tau_s``) in s. ``log``: c·log10(1 + (t − t_j)/t₀), c in nm per decade,
    t₀ (``t0_s``) in s. One amplitude shared by the events of the kind, or
    one per event (``each``).
    """

    kind: ClassVar[str]
    shape: ClassVar[str]
    each: ClassVar[bool] = False
    #: Before its third frame an event's column is small on one or two frames,
    #: and its amplitude is held at 0 unless clearly determined (|β| ≥ 3σ).
    min_column_support = 3

    def driver(self) -> dict[str, str]:
        return {"event_kind": self.kind, "shape": self.shape}

    def _times(self, history: History) -> FloatArray:
        return history.of_kind(self.kind)[0]

    def missing(self, history: History) -> str | None:
        if not history.of_kind(self.kind)[0].size:
            return f"no {self.kind} event logged"
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
        times = self._times(history)
        if times.size == 0:
            return np.zeros((t_s.size, 0))
        p = self._params(params)
        dt = t_s[:, None] - times[None, :]
        on = dt > 0
        dtp = np.where(on, dt, 0.0)
        if self.shape == "settle":
            cols = -np.expm1(-dtp / float(p["tau_s"]))
        else:
            cols = np.log10(1.0 + dtp / float(p["t0_s"]))
        cols = np.where(on, cols, 0.0)
        if self.each:
            return np.asarray(cols, dtype=np.float64)
        return np.asarray(cols.sum(axis=1)[:, None], dtype=np.float64)


class DriftShape(GenericTerm):
    """A shape of the drift itself at a time or a period: a cycle, a jump, a kink.

    ``periodic``: a·sin(2πt/P) + b·cos(2πt/P), P (``period_s``) in s, a and b
    in nm. ``jump``: A·H(t − t_j), A in nm, t_j (``t_s``) in s. ``rate_change``:
    r·max(0, t − t_k)/3600, r in nm/h, t_k (``t_s``) in s. Times are on the
    session's clock.
    """

    shape: ClassVar[str]
    #: The name of its one nonlinear parameter: ``period_s`` or ``t_s``.
    where: ClassVar[str]
    #: A jump or a kink is a column that starts at one moment: right after it
    #: its coefficient is held at 0 unless clearly determined, like an event's.
    min_column_support = 3

    def driver(self) -> dict[str, str]:
        return {"drift_shape": self.shape}

    def nonlinear_grid(self) -> list[dict[str, float]]:
        """The parameter's grid; an instance's ``searched`` values (s) replace it
        (``afmdrift diagnose`` searches a jump at every frame boundary)."""
        searched = vars(self).get("searched")
        if searched is not None:
            return [{self.where: float(v)} for v in searched]
        return super().nonlinear_grid()

    def design(
        self,
        t_s: FloatArray,
        history: History,
        *,
        scan_sign: FloatArray,
        params: Mapping[str, float],
        axis: int,
    ) -> FloatArray:
        value = float(self._params(params)[self.where])
        t = np.asarray(t_s, dtype=np.float64)
        if self.shape == "periodic":
            phase = 2.0 * np.pi * t / value
            return np.column_stack([np.sin(phase), np.cos(phase)])
        if self.shape == "jump":
            return np.asarray((t > value)[:, None], dtype=np.float64)
        return np.maximum(t - value, 0.0)[:, None] / 3600.0


#: The drift-shape families: (parameter, coefficient units, default search range in s).
_SHAPE_FAMILIES: dict[str, tuple[str, tuple[str, ...], tuple[float, float]]] = {
    "periodic": ("period_s", ("sin_nm", "cos_nm"), (600.0, 14400.0)),
    "jump": ("t_s", ("step_nm",), (1.0, 86400.0)),
    "rate_change": ("t_s", ("rate_change_nm_per_h",), (1.0, 86400.0)),
}


def is_term_spec(name: str) -> bool:
    """True if ``name`` is written as a generic term spec (``channel:``,
    ``event:``, ``periodic:``, ``jump:`` or ``rate_change:``)."""
    return name.strip().startswith(("channel:", "event:", *(f"{f}:" for f in _SHAPE_FAMILIES)))


def _unit_of(channel: str) -> str:
    """The unit suffix of a channel name (``pressure_hpa`` → ``hpa``), or ``unit``."""
    _, sep, unit = channel.rpartition("_")
    return unit if sep and unit and unit.isalnum() else "unit"


def _range(spec: str, part: str, value: str) -> tuple[float, float]:
    lo_s, sep, hi_s = value.partition("..")
    try:
        lo = float(lo_s)
        hi = float(hi_s) if sep else lo
    except ValueError:
        raise ConfigError(
            f"term spec {spec!r}: {part!r} needs a number or a range '<lo>..<hi>' in s"
        ) from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        raise ConfigError(f"term spec {spec!r}: {part!r} must be positive and finite with lo <= hi")
    return lo, hi


def _term_from_spec(spec: str, state: dict[str, Any]) -> GenericTerm:
    """A generic term of ``spec`` with the instance state ``state`` (unpickling)."""
    cls = parse_term_spec(spec)
    term = cls.__new__(cls)
    vars(term).update(state)
    return term


@functools.lru_cache(maxsize=512)
def parse_term_spec(spec: str) -> type[GenericTerm]:
    """The term class of a generic term spec (syntax in the module docstring).

    The class is built once per spec (cached), with ``name`` = ``spec``.

    Raises
    ------
    ConfigError
        A malformed spec; the message names the spec and the offending part.
    """
    text = spec.strip()
    body, hash_, label = text.partition("#")
    if hash_ and (not label or not set(label) <= _NAME_CHARS):
        raise ConfigError(
            f"term spec {spec!r}: label {label!r} must be lower-case letters, digits or '_'"
        )
    parts = body.split(":")
    family = parts[0]
    if family in _SHAPE_FAMILIES:
        return _shape_class(spec, text, family, parts[1:])
    if family not in ("channel", "event") or len(parts) < 2 or not parts[1]:
        raise ConfigError(
            f"term spec {spec!r}: expected 'channel:<channel>[:options]', "
            "'event:<kind>[:options]', 'periodic:period_s=<s>', 'jump:t_s=<s>' or "
            "'rate_change:t_s=<s>'"
        )
    driver = parts[1]
    shape = "settle"
    each = False
    ranges: dict[str, tuple[float, float]] = {}
    for opt in parts[2:]:
        key, eq, value = opt.partition("=")
        if eq:
            allowed = ("tau_s",) if family == "channel" else ("tau_s", "t0_s")
            if key not in allowed:
                raise ConfigError(
                    f"term spec {spec!r}: unknown parameter {key!r} (allowed: {', '.join(allowed)})"
                )
            ranges[key] = _range(spec, opt, value)
        elif family == "event" and opt in _SHAPES:
            shape = opt
        elif family == "event" and opt == "each":
            each = True
        else:
            allowed_opts = "tau_s=..." if family == "channel" else "settle, log, each, tau_s=..."
            raise ConfigError(
                f"term spec {spec!r}: unknown option {opt!r} (allowed: {allowed_opts})"
            )
    if family == "channel":
        if any(c.isspace() or c in ",#=" for c in driver):
            raise ConfigError(
                f"term spec {spec!r}: channel {driver!r} must not contain spaces, ',', '#' or '='"
            )
        return _channel_class(text, driver, ranges)
    try:
        kind = str(event_kind(driver))
    except ValueError as err:
        raise ConfigError(f"term spec {spec!r}: {err}") from None
    return _event_class(text, kind, shape, each, ranges)


def _param(
    spec: str, name: str, ranges: dict[str, tuple[float, float]], default: tuple[float, float]
) -> tuple[tuple[NonlinearParam, ...], dict[str, float]]:
    """The searched parameter, or its fixed value when the spec gives one value."""
    lo, hi = ranges.get(name, default)
    if lo == hi:
        return (), {name: lo}
    decades = math.log10(hi / lo)
    points = max(3, min(19, round(3.5 * decades) + 1))
    start = math.sqrt(lo * hi)
    return (NonlinearParam(name, lo, hi, start, grid_points=points),), {}


def _channel_class(
    spec: str, channel: str, ranges: dict[str, tuple[float, float]]
) -> type[GenericTerm]:
    nonlinear, fixed = _param(spec, "tau_s", ranges, CHANNEL_TAU_RANGE_S)
    doc = (
        f"Response to the logged channel {channel}, proportional through a first-order lag.\n\n"
        f"p(t) = g·(C_s(t) − C₀), τ·dC_s/dt = {channel}(t) − C_s; g in nm per "
        f"{_unit_of(channel)}, τ (tau_s, s) ≤ {CHANNEL_TAU_RANGE_S[0]:g} s is no lag."
    )
    attrs = {
        "name": spec,
        "channel": channel,
        "nonlinear_params": nonlinear,
        "fixed_params": fixed,
        "coefficient_units": (f"gain_nm_per_{_unit_of(channel)}",),
        "__doc__": doc,
        "__module__": __name__,
    }
    return type("ChannelResponseTerm", (ChannelResponse,), attrs)


def _event_class(
    spec: str, kind: str, shape: str, each: bool, ranges: dict[str, tuple[float, float]]
) -> type[GenericTerm]:
    if shape == "settle":
        if "t0_s" in ranges:
            raise ConfigError(f"term spec {spec!r}: the settle shape has tau_s, not t0_s")
        nonlinear, fixed = _param(spec, "tau_s", ranges, SETTLE_TAU_RANGE_S)
        units = ("amplitude_nm",)
        eq = "A·(1 − exp(−(t − t_j)/τ)), A in nm, τ (tau_s) in s"
    else:
        if "tau_s" in ranges:
            raise ConfigError(f"term spec {spec!r}: the log shape has t0_s, not tau_s")
        nonlinear, fixed = _param(spec, "t0_s", ranges, LOG_T0_RANGE_S)
        units = ("nm_per_decade",)
        eq = "c·log10(1 + (t − t_j)/t₀), c in nm per decade, t₀ (t0_s) in s"
    per = "one amplitude per event" if each else "one amplitude shared by every event"
    what = "exponential settling" if shape == "settle" else "logarithmic creep"
    doc = f"Response to each logged {kind} event ({what}).\n\np(t) = Σ_j {eq}; {per}."
    attrs = {
        "name": spec,
        "kind": kind,
        "shape": shape,
        "each": each,
        "nonlinear_params": nonlinear,
        "fixed_params": fixed,
        "coefficient_units": units,
        "__doc__": doc,
        "__module__": __name__,
    }
    return type("EventResponseTerm", (EventResponse,), attrs)


def _shape_class(spec: str, text: str, family: str, options: list[str]) -> type[GenericTerm]:
    """The class of a drift-shape spec (``periodic:period_s=1860``, ``jump:t_s=19200``)."""
    where, units, default = _SHAPE_FAMILIES[family]
    if len(options) != 1 or options[0].partition("=")[0] != where or "=" not in options[0]:
        raise ConfigError(f"term spec {spec!r}: expected '{family}:{where}=<value in s>'")
    value = options[0].partition("=")[2]
    nonlinear, fixed = _param(spec, where, {where: _range(spec, options[0], value)}, default)
    what = {
        "periodic": "a cycle of the drift: a·sin(2πt/P) + b·cos(2πt/P), a and b in nm",
        "jump": "a jump of the drift: A·H(t − t_j), A in nm",
        "rate_change": "a change of the drift rate: r·max(0, t − t_k)/3600, r in nm/h",
    }[family]
    attrs = {
        "name": text,
        "shape": family,
        "where": where,
        "nonlinear_params": nonlinear,
        "fixed_params": fixed,
        "coefficient_units": units,
        "__doc__": f"{what[0].upper()}{what[1:]}; {where} in s from the session's start.",
        "__module__": __name__,
    }
    return type("DriftShapeTerm", (DriftShape,), attrs)
