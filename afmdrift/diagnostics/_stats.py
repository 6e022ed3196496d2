"""Statistics of one-step prediction errors: summaries, whiteness, episodes.

Everything here works on the one-step errors e_k = p_k − p̂_k (measured minus
predicted drift position at frame k, predicted before frame k arrived), shape
(n, 2) for (x, y), at frame times t_k.

* :func:`error_summary`: mean |e|, RMS and peak of the Euclidean error.
* :func:`ljung_box`: Ljung & Box (1978) portmanteau test of residual
  autocorrelation, Q = n(n+2) Σ_{h≤L} ρ̂_h²/(n−h) ~ χ²_L under whiteness.
* :func:`lomb_scargle`: periodogram of unevenly sampled errors (Lomb 1976,
  Scargle 1982), normalised to the fraction of variance explained by a
  sinusoid at each period.
* :func:`cusum`: Page's (1954) two-sided CUSUM of standardised errors,
  S⁺_k = max(0, S⁺_{k−1} + z_k − κ), S⁻_k = max(0, S⁻_{k−1} − z_k − κ),
  alarm when either exceeds h.
* :func:`find_episodes`: contiguous runs of frames whose error is an outlier
  (robust z-score, median/MAD) or inside a CUSUM alarm, each linked to what
  was logged then (events, channel ramps, scan direction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy import special

from afmdrift.diagnostics._data import RunData
from afmdrift.records import Event, EventKind

__all__ = [
    "Failure",
    "cross_correlation",
    "cusum",
    "error_summary",
    "find_episodes",
    "ljung_box",
    "lomb_scargle",
    "robust_z",
]

FloatArray = npt.NDArray[np.float64]

#: Robust z-score above which a frame's error counts as a failure.
OUTLIER_Z = 3.5
#: CUSUM reference value κ and decision interval h (in robust σ units).
CUSUM_KAPPA = 1.0
CUSUM_H = 5.0


def error_summary(e_nm: FloatArray) -> dict[str, float]:
    """Summary of one-step errors (rows with a NaN are skipped).

    Parameters
    ----------
    e_nm : ndarray, shape (n, 2)
        Errors (x, y), nm.

    Returns
    -------
    dict
        ``n``, ``mean_abs_nm`` (mean Euclidean |e|), ``rmse_nm`` (RMS of the
        Euclidean |e|), ``rmse_x_nm``, ``rmse_y_nm``, ``peak_nm`` (max |e|).
    """
    e = np.asarray(e_nm, dtype=np.float64).reshape(-1, 2)
    e = e[np.all(np.isfinite(e), axis=1)]
    if e.shape[0] == 0:
        nan = math.nan
        return {
            "n": 0,
            "mean_abs_nm": nan,
            "rmse_nm": nan,
            "rmse_x_nm": nan,
            "rmse_y_nm": nan,
            "peak_nm": nan,
        }
    norm = np.hypot(e[:, 0], e[:, 1])
    return {
        "n": int(e.shape[0]),
        "mean_abs_nm": float(norm.mean()),
        "rmse_nm": float(np.sqrt(np.mean(norm**2))),
        "rmse_x_nm": float(np.sqrt(np.mean(e[:, 0] ** 2))),
        "rmse_y_nm": float(np.sqrt(np.mean(e[:, 1] ** 2))),
        "peak_nm": float(norm.max()),
    }


def robust_z(x: FloatArray) -> FloatArray:
    """(x − median)/(1.4826·MAD), shape of ``x``; NaN stays NaN.

    A zero MAD (more than half the values equal) falls back to the standard
    deviation, and to 1 if that is zero too.
    """
    v = np.asarray(x, dtype=np.float64)
    ok = np.isfinite(v)
    if not ok.any():
        return np.full_like(v, np.nan)
    med = float(np.median(v[ok]))
    mad = 1.4826 * float(np.median(np.abs(v[ok] - med)))
    if mad <= 0:
        mad = float(np.std(v[ok])) or 1.0
    return (v - med) / mad


def ljung_box(e: FloatArray, *, lags: int | None = None) -> tuple[float, float, int]:
    """Ljung–Box Q statistic, its p-value and the number of lags used.

    Parameters
    ----------
    e : ndarray, shape (n,)
        One axis of the errors (NaN skipped).
    lags : int, optional
        Default min(10, n // 5).
    """
    v = np.asarray(e, dtype=np.float64)
    v = v[np.isfinite(v)]
    n = v.size
    lag = min(10, n // 5) if lags is None else int(lags)
    if n < 8 or lag < 1 or float(np.std(v)) == 0.0:
        return math.nan, math.nan, 0
    lag = min(lag, n - 1)
    d = v - v.mean()
    c0 = float(d @ d)
    rho = np.array([float(d[h:] @ d[:-h]) / c0 for h in range(1, lag + 1)])
    q = float(n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, lag + 1))))
    return q, float(special.chdtrc(lag, q)), lag


def lomb_scargle(
    t_s: FloatArray, e: FloatArray, *, n_periods: int = 200
) -> tuple[FloatArray, FloatArray]:
    """Normalised Lomb–Scargle periodogram of unevenly sampled errors.

    Periods run log-spaced from 2× the median sampling interval to the record
    length. Power is the fraction of the variance a sinusoid at that period
    explains (0..1).

    Returns
    -------
    period_s : ndarray, shape (m,)
    power : ndarray, shape (m,)
    """
    t = np.asarray(t_s, dtype=np.float64)
    v = np.asarray(e, dtype=np.float64)
    ok = np.isfinite(t) & np.isfinite(v)
    t, v = t[ok], v[ok]
    if t.size < 8 or float(np.std(v)) == 0.0:
        return np.zeros(0), np.zeros(0)
    dt = float(np.median(np.diff(t)))
    span = float(t[-1] - t[0])
    periods = np.geomspace(2.0 * dt, span, n_periods)
    return periods, _lomb_power(t - t[0], v - v.mean(), 2.0 * np.pi / periods)


def _lomb_power(t: FloatArray, y: FloatArray, omega: FloatArray) -> FloatArray:
    """Lomb's normalised power at each angular frequency: with the offset τ of
    tan 2ωτ = Σ sin 2ωt / Σ cos 2ωt, P = [(Σ y cos ω(t−τ))² / Σ cos² ω(t−τ)
    + (Σ y sin ω(t−τ))² / Σ sin² ω(t−τ)] / Σ y² (scipy's ``lombscargle`` with
    ``normalize=True``, which the tests check; importing ``scipy.signal``
    took a second of every diagnosis)."""
    wt = omega[:, None] * t[None, :]
    tau = 0.5 * np.arctan2(np.sin(2.0 * wt).sum(axis=1), np.cos(2.0 * wt).sum(axis=1))
    arg = wt - tau[:, None]
    c, s = np.cos(arg), np.sin(arg)
    yc, ys = c @ y, s @ y
    cc, ss = (c * c).sum(axis=1), (s * s).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(cc > 0, yc**2 / cc, 0.0) + np.where(ss > 0, ys**2 / ss, 0.0)
    return np.asarray(p / float(y @ y), dtype=np.float64)


def cusum(
    z: FloatArray, *, kappa: float = CUSUM_KAPPA, h: float = CUSUM_H
) -> tuple[FloatArray, FloatArray, list[tuple[int, int]]]:
    """Two-sided CUSUM of standardised values and its alarm segments.

    Returns
    -------
    s_pos, s_neg : ndarray, shape (n,)
        Upper and lower cumulative sums (NaN input counts as 0).
    segments : list of (start, stop)
        Index ranges ``[start, stop]`` (inclusive) of each alarmed excursion:
        from where the sum left zero (the change-point estimate) to where it
        peaked before falling back.
    """
    v = np.nan_to_num(np.asarray(z, dtype=np.float64))
    n = v.size
    s_pos = np.zeros(n)
    s_neg = np.zeros(n)
    for k in range(n):
        prev_p = s_pos[k - 1] if k else 0.0
        prev_n = s_neg[k - 1] if k else 0.0
        s_pos[k] = max(0.0, prev_p + v[k] - kappa)
        s_neg[k] = max(0.0, prev_n - v[k] - kappa)
    segments: list[tuple[int, int]] = []
    for s in (s_pos, s_neg):
        k = 0
        while k < n:
            if s[k] > h:
                start = k
                while start > 0 and s[start - 1] > 0:
                    start -= 1
                end = k
                while end + 1 < n and s[end + 1] > 0:
                    end += 1
                stop = start + int(np.argmax(s[start : end + 1]))
                segments.append((start, stop))
                k = end + 1
            else:
                k += 1
    return s_pos, s_neg, segments


def cross_correlation(
    e: FloatArray, x: FloatArray, *, max_lag: int
) -> tuple[npt.NDArray[np.int64], FloatArray]:
    """Correlation of ``e[k]`` with ``x[k − lag]`` for lag in −max_lag..max_lag.

    Both are series at the same frame times (NaN rows skipped pairwise). A
    positive lag means the error follows the channel.
    """
    a = np.asarray(e, dtype=np.float64)
    b = np.asarray(x, dtype=np.float64)
    lags = np.arange(-max_lag, max_lag + 1, dtype=np.int64)
    out = np.full(lags.size, np.nan)
    for i, lag in enumerate(lags):
        if lag >= 0:
            u, w = a[lag:], b[: b.size - lag]
        else:
            u, w = a[: a.size + lag], b[-lag:]
        ok = np.isfinite(u) & np.isfinite(w)
        if ok.sum() >= 5 and np.std(u[ok]) > 0 and np.std(w[ok]) > 0:
            out[i] = float(np.corrcoef(u[ok], w[ok])[0, 1])
    return lags, out


@dataclass(frozen=True, slots=True)
class Failure:
    """A time interval where the model fails, with what was happening then.

    Attributes
    ----------
    t_start_s, t_end_s : float
        Mid-scan times of the first and last frame of the episode, s.
    frames : list of int
        Frame numbers in the episode.
    peak_error_nm : float
        Largest Euclidean one-step error inside, nm.
    kind : str
        ``"outlier"`` (single large errors) or ``"sustained"`` (CUSUM alarm).
    note : str
        Plain-language context.
    context : list of str
        Machine-readable tags: ``offset_move``, ``manipulation``,
        ``tip_change``, ``power_on``, ``ramp:<channel>``, ``up_frames``,
        ``down_frames``.
    """

    t_start_s: float
    t_end_s: float
    frames: list[int]
    peak_error_nm: float
    kind: str
    note: str
    context: list[str] = field(default_factory=list)


def _local_rates(data: RunData, name: str, t_s: FloatArray, half_s: float) -> FloatArray:
    """Slope of channel ``name`` (units per hour) in ±``half_s`` around each time."""
    ct, cv = data.channel_series(name)
    out = np.full(t_s.size, np.nan)
    if ct.size < 3:
        return out
    for i, t in enumerate(t_s):
        sel = (ct >= t - half_s) & (ct <= t + half_s)
        if sel.sum() >= 3 and np.ptp(ct[sel]) > 0:
            out[i] = float(np.polyfit(ct[sel], cv[sel], 1)[0]) * 3600.0
    return out


def find_episodes(
    data: RunData,
    t_s: FloatArray,
    frames: npt.NDArray[np.int64],
    e_nm: FloatArray,
    scan_sign: FloatArray,
    *,
    z_threshold: float = OUTLIER_Z,
) -> list[Failure]:
    """Failure episodes of one-step errors, each with a note on its context.

    Parameters
    ----------
    data : RunData
        Source of events and channels.
    t_s : ndarray, shape (n,)
        Frame times of the errors, s.
    frames : ndarray of int, shape (n,)
        Frame numbers.
    e_nm : ndarray, shape (n, 2)
        One-step errors (NaN rows: no prediction), nm.
    scan_sign : ndarray, shape (n,)
        +1 up, −1 down.
    z_threshold : float
        Robust z-score above which a single error is a failure.
    """
    e = np.asarray(e_nm, dtype=np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(e), axis=1)
    if ok.sum() < 8:
        return []
    flag, kind = _flag_frames(e, ok, z_threshold=z_threshold)
    logged = _Logged.of(data, t_s, scan_sign)
    return [
        _episode(g, logged, t_s=t_s, frames=frames, e_nm=e, kind=kind)
        for g in _group_runs(np.flatnonzero(flag))
    ]


def _flag_frames(
    e: FloatArray, ok: npt.NDArray[np.bool_], *, z_threshold: float
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.object_]]:
    """Flag outlier frames, then CUSUM-alarmed frames, and label each flag's kind.

    Parameters
    ----------
    e : ndarray, shape (n, 2)
        One-step errors, nm.
    ok : ndarray of bool, shape (n,)
        Rows of ``e`` without NaN.
    z_threshold : float
        Robust z-score above which a single error is an outlier.

    Returns
    -------
    flag : ndarray of bool, shape (n,)
    kind : ndarray of str (object), shape (n,)
        ``"outlier"``, ``"sustained"`` or ``""`` (not flagged); an outlier
        keeps its kind when a CUSUM alarm covers it too.
    """
    z = np.column_stack([robust_z(e[:, a]) for a in (0, 1)])
    flag = np.zeros(e.shape[0], dtype=bool)
    kind = np.array([""] * e.shape[0], dtype=object)
    out_mask = ok & (np.nanmax(np.abs(z), axis=1) > z_threshold)
    flag |= out_mask
    kind[out_mask] = "outlier"
    for a in (0, 1):
        # Outliers are flagged on their own; clipped, they cannot raise a CUSUM alarm alone.
        zz = np.clip(np.where(ok, z[:, a], 0.0), -z_threshold, z_threshold)
        _, _, segs = cusum(zz)
        for s0, s1 in segs:
            sel = np.zeros_like(flag)
            sel[s0 : s1 + 1] = True
            sel &= ~flag
            flag |= sel
            kind[sel] = "sustained"
    return flag, kind


def _group_runs(idx: npt.NDArray[np.intp]) -> list[list[int]]:
    """Sorted indices grouped into runs, a gap of at most one index allowed inside."""
    groups: list[list[int]] = []
    for i in idx:
        if groups and i - groups[-1][-1] <= 2:
            groups[-1].append(int(i))
        else:
            groups.append([int(i)])
    return groups


@dataclass(frozen=True, slots=True)
class _Logged:
    """What the run logged, at the error frames, for describing an episode.

    Attributes
    ----------
    events : list of Event
        The run's events.
    step_s : float
        Median frame interval, s (1 with a single frame).
    names : list of str
        Channel names, in the run's order.
    rates : dict of str to ndarray, shape (n,)
        Local slope of each channel at each frame, units per hour.
    typical : dict of str to float
        Median |rate| of each channel over the run, units per hour.
    scan_sign : ndarray, shape (n,)
        +1 up, −1 down.
    alternating : bool
        Whether the frames have both scan directions.
    """

    events: list[Event]
    step_s: float
    names: list[str]
    rates: dict[str, FloatArray]
    typical: dict[str, float]
    scan_sign: FloatArray
    alternating: bool

    @classmethod
    def of(cls, data: RunData, t_s: FloatArray, scan_sign: FloatArray) -> _Logged:
        """Channel rates over ± one frame interval, and the run's events and directions."""
        step = float(np.median(np.diff(t_s))) if t_s.size > 1 else 1.0
        names = data.channel_names()
        rates = {nm: _local_rates(data, nm, t_s, step) for nm in names}
        typical = {
            nm: float(np.nanmedian(np.abs(r))) if np.isfinite(r).any() else 0.0
            for nm, r in rates.items()
        }
        alternating = bool(np.any(scan_sign > 0) and np.any(scan_sign < 0))
        return cls(data.events, step, names, rates, typical, scan_sign, alternating)

    def describe(self, g: list[int], t0_s: float, t1_s: float) -> tuple[list[str], list[str]]:
        """Tags and plain-language notes for the frames ``g`` (from ``t0_s`` to ``t1_s``).

        Events come first, then channel ramps, then the scan direction.
        """
        tags, parts = self._event_notes(t0_s, t1_s)
        for more_tags, more_parts in (self._ramp_notes(g), self._direction_notes(g)):
            tags += more_tags
            parts += more_parts
        return tags, parts

    def _ramp_notes(self, g: list[int]) -> tuple[list[str], list[str]]:
        """Channels changing over ``g`` faster than twice their typical rate."""
        tags: list[str] = []
        parts: list[str] = []
        for nm in self.names:
            r = self.rates[nm][g[0] : g[-1] + 1]
            if not np.isfinite(r).any():
                continue
            mean_rate = float(np.nanmean(r))
            if abs(mean_rate) > 2.0 * self.typical[nm] and abs(mean_rate) > 0:
                tags.append(f"ramp:{nm}")
                parts.append(
                    f"{nm} changing at {mean_rate:+.3g}/h (typical {self.typical[nm]:.2g}/h)"
                )
        return tags, parts

    def _direction_notes(self, g: list[int]) -> tuple[list[str], list[str]]:
        """Whether ``g`` holds only up or only down frames (when the run alternates)."""
        if not self.alternating:
            return [], []
        signs = self.scan_sign[g]
        if np.all(signs > 0):
            return ["up_frames"], ["on up frames only" if len(g) > 1 else "on an up frame"]
        if np.all(signs < 0):
            return ["down_frames"], ["on down frames only" if len(g) > 1 else "on a down frame"]
        return [], []

    def _event_notes(self, t0_s: float, t1_s: float) -> tuple[list[str], list[str]]:
        """Events from two frame intervals before ``t0_s`` to ``t1_s``: tags and notes."""
        tags: list[str] = []
        parts: list[str] = []
        moves = [
            e
            for e in self.events
            if e.kind is EventKind.OFFSET_MOVE and t0_s - 2.0 * self.step_s <= e.t_s <= t1_s
        ]
        for ev in self.events:
            if t0_s - 2.0 * self.step_s <= ev.t_s <= t1_s:
                tag = str(ev.kind)
                if tag not in tags:
                    tags.append(tag)
                if tag == "offset_move" and len(moves) > _MOVES_LISTED:
                    continue
                when = _when(t0_s - ev.t_s, ev.t_s)
                if tag == "offset_move":
                    parts.append(f"offset move of ({ev.x_nm:+.0f}, {ev.y_nm:+.0f}) nm {when}")
                else:
                    parts.append(f"{tag.replace('_', ' ')} {when}")
        if len(moves) > _MOVES_LISTED:
            # a closed loop moves every few seconds: one line for all of them
            net = (sum(e.x_nm for e in moves), sum(e.y_nm for e in moves))
            first = _when(t0_s - moves[0].t_s, moves[0].t_s)
            parts.append(
                f"{len(moves)} offset moves (a closed loop?) adding up to "
                f"({net[0]:+.0f}, {net[1]:+.0f}) nm, the first {first}"
            )
        return tags, parts


#: More offset moves than this in one episode are summed in one note.
_MOVES_LISTED = 3


def _when(dt_s: float, t_s: float) -> str:
    """How long before an episode (starting ``dt_s`` after ``t_s``) an event was."""
    if dt_s < 0:
        return f"inside, at t = {t_s:.0f} s"
    if dt_s < 90:
        return f"{dt_s:.0f} s before"
    return f"{dt_s / 60:.0f} min before"


def _episode(
    g: list[int],
    logged: _Logged,
    *,
    t_s: FloatArray,
    frames: npt.NDArray[np.int64],
    e_nm: FloatArray,
    kind: npt.NDArray[np.object_],
) -> Failure:
    """The :class:`Failure` of the flagged frames ``g`` (indices into ``t_s``)."""
    t0, t1 = float(t_s[g[0]]), float(t_s[g[-1]])
    norm = np.hypot(e_nm[g, 0], e_nm[g, 1])
    peak = float(np.nanmax(norm)) if np.isfinite(norm).any() else math.nan
    kinds = {str(kind[i]) for i in g}
    k = "sustained" if "sustained" in kinds else "outlier"
    tags, parts = logged.describe(g, t0, t1)
    what = (
        f"{len(g)} frame(s) with large one-step errors (peak {peak:.2f} nm)"
        if k == "outlier"
        else f"sustained bias over {len(g)} frames (peak {peak:.2f} nm)"
    )
    context = "; ".join(parts) if parts else "no logged event or channel ramp nearby"
    return Failure(
        t_start_s=t0,
        t_end_s=t1,
        frames=[int(frames[i]) for i in g],
        peak_error_nm=peak,
        kind=k,
        note=f"{what}: {context}",
        context=tags,
    )


def welch_p(a: FloatArray, b: FloatArray) -> float:
    """Two-sided p-value of Welch's t-test of equal means (unequal variances,
    Welch–Satterthwaite degrees of freedom); 1 when both samples are constant."""
    na, nb = a.size, b.size
    va, vb = float(np.var(a, ddof=1)) / na, float(np.var(b, ddof=1)) / nb
    se2 = va + vb
    diff = float(a.mean() - b.mean())
    if not se2 > 0:
        return 1.0 if diff == 0 else 0.0
    df = se2**2 / (va**2 / (na - 1) + vb**2 / (nb - 1))
    t = diff / math.sqrt(se2)
    return float(2.0 * special.stdtr(df, -abs(t)))


def up_down_difference(e_nm: FloatArray, scan_sign: FloatArray) -> dict[str, float] | None:
    """Mean error of up minus down frames per axis and Welch's t-test p-value.

    Returns None when the run has only one scan direction.
    """
    e = np.asarray(e_nm, dtype=np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(e), axis=1)
    up = ok & (scan_sign > 0)
    dn = ok & (scan_sign < 0)
    if up.sum() < 3 or dn.sum() < 3:
        return None
    out: dict[str, float] = {}
    p_min = 1.0
    for a, name in enumerate("xy"):
        d = float(e[up, a].mean() - e[dn, a].mean())
        p = welch_p(e[up, a], e[dn, a])
        out[f"diff_{name}_nm"] = d
        p_min = min(p_min, p)
    out["p_value"] = min(1.0, 2.0 * p_min)
    return out
