"""The continuous drift offset d(t) handed to the tip controller.

Measurements arrive once per frame; the tip needs an offset at every instant.
After each frame afmdrift publishes an :class:`OffsetCurve` that the client
evaluates at any time until the next one arrives. Two constructions:

``sinc`` — eq. (12) of Yang et al. (2008), exactly as published::

    d(t) = Σᵢ dᵢ · sinc(π(t − tᵢ)/Δt),    sinc(x) = sin(x)/x,  sinc(0) = 1,

over the measured samples dᵢ at tᵢ (uniform spacing Δt, the frame period)
followed by ``lookahead`` predicted samples. It interpolates every sample
exactly, but it is non-causal (d(t) depends on samples after t, so only the
predicted ones can stand in for the future), and a finite sum of sincs rings
near the ends of the window: beyond the last sample d(t) decays towards 0
(the sum of sincs is not a partition of unity), and between the last samples
it oscillates with an amplitude of order of the drift itself (Gibbs-like
ringing at a truncated band-limited series).

``hermite`` — causal, piecewise cubic Hermite. At publication time t₀ the
curve starts from the value and slope of the previously published curve at t₀
(so d and d′ are continuous across publications: the tip never jumps), and
passes through the predicted positions at the next ``lookahead`` frame times
with the predictor's slopes, limited by the Fritsch–Carlson rule so that the
curve is monotone wherever the knots are (no overshoot at the window edge).
Beyond its last knot it continues linearly with the last slope. It only uses
measured samples up to now and predictions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from afmdrift.config import ModelConfig
from afmdrift.errors import InputError
from afmdrift.model._base import History, Predictor

__all__ = [
    "OffsetCurve",
    "build_offset_curve",
    "hermite_curve",
    "reconstruct_offset",
    "sinc_curve",
    "sinc_reconstruct",
]

FloatArray = npt.NDArray[np.float64]

CURVE_FORMAT = "afmdrift-offset-curve"
CURVE_VERSION = 1


def sinc_reconstruct(
    t_s: npt.ArrayLike, sample_t_s: npt.ArrayLike, samples_nm: npt.ArrayLike, *, dt_s: float
) -> FloatArray:
    """Eq. (12) of Yang et al. (2008): d(t) = Σ dᵢ sinc(π(t − tᵢ)/Δt).

    Parameters
    ----------
    t_s : array_like, shape (n,)
        Evaluation times, s.
    sample_t_s : array_like, shape (m,)
        Sample times tᵢ, s (uniformly spaced by ``dt_s`` for the formula to
        interpolate; the formula is applied as written regardless).
    samples_nm : array_like, shape (m, 2)
        Samples dᵢ (x, y), nm.
    dt_s : float
        Sample spacing Δt, s.

    Returns
    -------
    ndarray, shape (n, 2)
    """
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt_s must be positive and finite, got {dt_s}")
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    ti = np.asarray(sample_t_s, dtype=np.float64)
    di = np.asarray(samples_nm, dtype=np.float64).reshape(-1, 2)
    # np.sinc(x) = sin(πx)/(πx), so np.sinc((t − tᵢ)/Δt) = sinc(π(t − tᵢ)/Δt).
    kernel = np.sinc((t[:, None] - ti[None, :]) / dt_s)
    return np.asarray(kernel @ di, dtype=np.float64)


def _hermite_eval(
    t: FloatArray, tk: FloatArray, yk: FloatArray, mk: FloatArray, *, derivative: bool
) -> FloatArray:
    out = np.zeros((t.size, 2))
    if tk.size == 1:
        out[:] = mk[0] if derivative else yk[0] + (t - tk[0])[:, None] * mk[0]
        return out
    before = t < tk[0]
    after = t > tk[-1]
    inside = ~(before | after)
    if before.any():
        out[before] = mk[0] if derivative else yk[0] + (t[before] - tk[0])[:, None] * mk[0]
    if after.any():
        out[after] = mk[-1] if derivative else yk[-1] + (t[after] - tk[-1])[:, None] * mk[-1]
    if inside.any():
        ti = t[inside]
        k = np.clip(np.searchsorted(tk, ti, side="right") - 1, 0, tk.size - 2)
        h = (tk[k + 1] - tk[k])[:, None]
        s = ((ti - tk[k])[:, None]) / h
        y0, y1, m0, m1 = yk[k], yk[k + 1], mk[k] * h, mk[k + 1] * h
        if derivative:
            h00 = 6 * s**2 - 6 * s
            h10 = 3 * s**2 - 4 * s + 1
            h01 = -6 * s**2 + 6 * s
            h11 = 3 * s**2 - 2 * s
            out[inside] = (h00 * y0 + h10 * m0 + h01 * y1 + h11 * m1) / h
        else:
            h00 = 2 * s**3 - 3 * s**2 + 1
            h10 = s**3 - 2 * s**2 + s
            h01 = -2 * s**3 + 3 * s**2
            h11 = s**3 - s**2
            out[inside] = h00 * y0 + h10 * m0 + h01 * y1 + h11 * m1
    return out


@dataclass(frozen=True, slots=True)
class OffsetCurve:
    """A published continuous offset d(t), evaluable at any time.

    Attributes
    ----------
    kind : {"sinc", "hermite"}
    t_valid_s : (float, float)
        Interval for which the curve was built (publication time to the last
        predicted sample); outside it the curve still evaluates (sinc: the
        formula; hermite: linear continuation) but a newer curve should exist.
    knot_t_s : ndarray, shape (k,)
        Sample times (sinc) or Hermite knots, s.
    knot_nm : ndarray, shape (k, 2)
        Sample values or knot values (x, y), nm.
    slope_nm_per_s : ndarray, shape (k, 2)
        Knot slopes (hermite only; zeros for sinc).
    dt_s : float
        Sample spacing Δt of the sinc formula (0 for hermite).
    """

    kind: Literal["sinc", "hermite"]
    t_valid_s: tuple[float, float]
    knot_t_s: FloatArray
    knot_nm: FloatArray
    slope_nm_per_s: FloatArray
    dt_s: float = 0.0

    def at(self, t_s: npt.ArrayLike) -> FloatArray:
        """d(t) at ``t_s``, shape (n, 2), nm."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64)).ravel()
        if self.kind == "sinc":
            return sinc_reconstruct(t, self.knot_t_s, self.knot_nm, dt_s=self.dt_s)
        return _hermite_eval(t, self.knot_t_s, self.knot_nm, self.slope_nm_per_s, derivative=False)

    def derivative(self, t_s: npt.ArrayLike) -> FloatArray:
        """d′(t) at ``t_s``, shape (n, 2), nm/s."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64)).ravel()
        if self.kind == "sinc":
            x = (t[:, None] - self.knot_t_s[None, :]) / self.dt_s
            with np.errstate(divide="ignore", invalid="ignore"):
                px = np.pi * x
                ds = np.where(np.abs(x) < 1e-8, 0.0, (np.cos(px) * px - np.sin(px)) / (px * x))
            return np.asarray(ds @ self.knot_nm / self.dt_s, dtype=np.float64)
        return _hermite_eval(t, self.knot_t_s, self.knot_nm, self.slope_nm_per_s, derivative=True)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (published on the service's ``model`` topic)."""
        return {
            "format": CURVE_FORMAT,
            "version": CURVE_VERSION,
            "kind": self.kind,
            "t_valid_s": [float(self.t_valid_s[0]), float(self.t_valid_s[1])],
            "knot_t_s": self.knot_t_s.tolist(),
            "knot_nm": self.knot_nm.tolist(),
            "slope_nm_per_s": self.slope_nm_per_s.tolist(),
            "dt_s": float(self.dt_s),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> OffsetCurve:
        """Inverse of :meth:`to_dict`; raises :class:`InputError` naming a bad field."""
        if d.get("format") != CURVE_FORMAT or d.get("version") != CURVE_VERSION:
            raise InputError(
                f"offset curve: expected format {CURVE_FORMAT!r} version {CURVE_VERSION}, "
                f"got {d.get('format')!r} version {d.get('version')!r}"
            )
        kind = d.get("kind")
        if kind not in ("sinc", "hermite"):
            raise InputError(f"offset curve: kind must be 'sinc' or 'hermite', got {kind!r}")
        try:
            tk = np.asarray(d["knot_t_s"], dtype=np.float64).ravel()
            yk = np.asarray(d["knot_nm"], dtype=np.float64).reshape(-1, 2)
            mk = np.asarray(d["slope_nm_per_s"], dtype=np.float64).reshape(-1, 2)
            valid = (float(d["t_valid_s"][0]), float(d["t_valid_s"][1]))
            dt = float(d["dt_s"])
        except (KeyError, TypeError, ValueError, IndexError) as err:
            raise InputError(f"offset curve: malformed field ({err})") from None
        if not (tk.size == yk.shape[0] == mk.shape[0]) or tk.size == 0:
            raise InputError(
                f"offset curve: {tk.size} knot times, {yk.shape[0]} values, "
                f"{mk.shape[0]} slopes; need the same nonzero number"
            )
        if kind == "sinc" and not dt > 0:
            raise InputError(f"offset curve: sinc needs dt_s > 0, got {dt}")
        return cls(kind, valid, tk, yk, mk, dt)


def sinc_curve(
    sample_t_s: npt.ArrayLike,
    samples_nm: npt.ArrayLike,
    *,
    dt_s: float,
    t_valid_s: tuple[float, float],
) -> OffsetCurve:
    """An :class:`OffsetCurve` evaluating eq. (12) over the given samples."""
    ti = np.asarray(sample_t_s, dtype=np.float64).ravel()
    di = np.asarray(samples_nm, dtype=np.float64).reshape(-1, 2)
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt_s must be positive and finite, got {dt_s}")
    return OffsetCurve("sinc", t_valid_s, ti, di, np.zeros_like(di), float(dt_s))


def _limit_slopes(
    tk: FloatArray, yk: FloatArray, mk: FloatArray, *, fixed_first: bool
) -> FloatArray:
    """Fritsch–Carlson limiter: slopes that keep each monotone segment monotone.

    Fritsch & Carlson, SIAM J. Numer. Anal. 17(2), 1980. The first knot's
    slope is left alone when ``fixed_first`` (it carries C1 continuity with the
    previous curve).
    """
    m = mk.copy()
    if tk.size < 2:
        return m
    delta = np.diff(yk, axis=0) / np.diff(tk)[:, None]
    for k in range(1 if fixed_first else 0, tk.size):
        for seg in (k - 1, k):
            if not 0 <= seg < delta.shape[0]:
                continue
            for axis in range(2):
                d = delta[seg, axis]
                if d == 0.0 or m[k, axis] * d < 0.0:
                    m[k, axis] = 0.0
                elif abs(m[k, axis]) > 3.0 * abs(d):
                    m[k, axis] = 3.0 * d
    return m


def hermite_curve(
    knot_t_s: npt.ArrayLike,
    knot_nm: npt.ArrayLike,
    slope_nm_per_s: npt.ArrayLike,
    *,
    fixed_first_slope: bool = True,
) -> OffsetCurve:
    """A cubic Hermite :class:`OffsetCurve` through the knots (slopes limited).

    Parameters
    ----------
    knot_t_s : array_like, shape (k,)
        Increasing knot times, s.
    knot_nm : array_like, shape (k, 2)
    slope_nm_per_s : array_like, shape (k, 2)
        Desired slopes; all but (if ``fixed_first_slope``) the first are
        limited by the Fritsch–Carlson rule.
    """
    tk = np.asarray(knot_t_s, dtype=np.float64).ravel()
    yk = np.asarray(knot_nm, dtype=np.float64).reshape(-1, 2)
    mk = np.asarray(slope_nm_per_s, dtype=np.float64).reshape(-1, 2)
    if tk.size == 0 or yk.shape[0] != tk.size or mk.shape[0] != tk.size:
        raise ValueError(
            f"hermite_curve: {tk.size} knot times, {yk.shape[0]} values, {mk.shape[0]} slopes"
        )
    if np.any(np.diff(tk) <= 0):
        raise ValueError(f"hermite_curve: knot times must increase, got {tk.tolist()}")
    mk = _limit_slopes(tk, yk, mk, fixed_first=fixed_first_slope)
    return OffsetCurve("hermite", (float(tk[0]), float(tk[-1])), tk, yk, mk, 0.0)


def build_offset_curve(
    method: Literal["hermite", "sinc"],
    predictor: Predictor,
    history: History,
    *,
    t_now_s: float,
    measured_t_s: npt.ArrayLike,
    measured_nm: npt.ArrayLike,
    frame_period_s: float,
    lookahead: int = 2,
    previous: OffsetCurve | None = None,
    blend_s: float | None = None,
) -> OffsetCurve:
    """Build the curve to publish after a frame has been measured.

    Parameters
    ----------
    method : {"hermite", "sinc"}
    predictor : Predictor
        Already updated with the latest measurement; its
        :meth:`~Predictor.predict_drift` (position without measurement
        artefacts) gives the predicted samples.
    history : History
    t_now_s : float
        Publication time (the curve is used from here on), s.
    measured_t_s, measured_nm : array_like, shapes (m,), (m, 2)
        Measured drift samples so far (the sinc formula uses them; the
        Hermite curve only uses the last time, to place the future knots).
    frame_period_s : float
        Δt between frames, s.
    lookahead : int
        Number of predicted future samples at t_last + jΔt, j = 1..lookahead.
    previous : OffsetCurve, optional
        The curve published before; the Hermite curve starts from its value and
        slope at ``t_now_s`` (C1 continuity across publications).
    blend_s : float, optional
        Hermite only: add a knot on the new prediction ``blend_s`` after
        ``t_now_s``, so the curve hands over from the previous one within
        ``blend_s`` instead of at the next frame time.
    """
    if not (math.isfinite(frame_period_s) and frame_period_s > 0):
        raise ValueError(f"frame_period_s must be positive, got {frame_period_s}")
    tm = np.asarray(measured_t_s, dtype=np.float64).ravel()
    dm = np.asarray(measured_nm, dtype=np.float64).reshape(-1, 2)
    if tm.size == 0:
        raise ValueError("build_offset_curve needs at least one measured sample")
    future = tm[-1] + frame_period_s * np.arange(1, lookahead + 1)
    if method == "sinc":
        pred = predictor.predict_drift(future, history).mean_nm
        return sinc_curve(
            np.concatenate([tm, future]),
            np.vstack([dm, pred]),
            dt_s=frame_period_s,
            t_valid_s=(float(t_now_s), float(future[-1])),
        )
    if blend_s is not None and blend_s > 0:
        # Reach the new prediction blend_s after publication, then follow it.
        future = np.concatenate([[t_now_s + blend_s], future[future > t_now_s + 1.05 * blend_s]])
    future = future[future > t_now_s + 0.05 * frame_period_s]
    if future.size == 0:
        future = np.array([t_now_s + frame_period_s])
    eps = 0.05 * frame_period_s
    probe = predictor.predict_drift(np.concatenate([future - eps, future, future + eps]), history)
    n = future.size
    values = probe.mean_nm[n : 2 * n]
    slopes = (probe.mean_nm[2 * n :] - probe.mean_nm[:n]) / (2 * eps)
    if previous is not None:
        y0 = previous.at([t_now_s])[0]
        m0 = previous.derivative([t_now_s])[0]
    else:
        start = predictor.predict_drift([t_now_s - eps, t_now_s, t_now_s + eps], history).mean_nm
        y0 = start[1]
        m0 = (start[2] - start[0]) / (2 * eps)
    return hermite_curve(
        np.concatenate([[t_now_s], future]),
        np.vstack([y0[None, :], values]),
        np.vstack([m0[None, :], slopes]),
    )


def reconstruct_offset(
    predictor: Predictor,
    history: History,
    *,
    config: ModelConfig,
    t_now_s: float,
    previous: OffsetCurve | None = None,
    min_blend_s: float = 0.0,
) -> OffsetCurve:
    """The curve to publish now, built as ``config`` (``[model]``) says.

    Convenience wrapper of :func:`build_offset_curve` for the service: the
    measured samples are the predictor's own observations
    (:meth:`Predictor.observed`), the frame period their median spacing, and
    the method and look-ahead come from ``config.reconstruction`` and
    ``config.lookahead``. Pass the previously published curve as ``previous``
    to keep d(t) and d′(t) continuous across publications; the Hermite curve
    hands over from it to the new prediction within ``blend_fraction`` of a
    frame period, or ``min_blend_s`` if that is longer (a model change,
    :meth:`afmdrift.pipeline.FramePipeline.use_model`).

    Raises
    ------
    ValueError
        If the predictor has no observations yet.
    """
    t_obs, xy_obs = predictor.observed()
    if t_obs.size == 0:
        raise ValueError(f"predictor {predictor.name!r} has no observations to reconstruct from")
    period = float(np.median(np.diff(t_obs))) if t_obs.size >= 2 else math.nan
    if not (math.isfinite(period) and period > 0):
        period = max(float(t_now_s - t_obs[-1]), 1.0)
    return build_offset_curve(
        config.reconstruction,
        predictor,
        history,
        t_now_s=t_now_s,
        measured_t_s=t_obs,
        measured_nm=xy_obs,
        frame_period_s=period,
        lookahead=config.lookahead,
        previous=previous,
        blend_s=max(config.blend_fraction * period, min_blend_s),
    )
