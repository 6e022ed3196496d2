"""A logged channel as the quantity it measures: the sensor's white noise removed.

A sensor log (the room thermometer every 10 s) is the physical quantity plus
read-out noise. The quantity a drift follows is smooth (a scanner's
temperature cannot jump between two readings), but its read-out noise is
not: a term k·(T − T₀) taken at face value passes k·noise into every fit and
prediction (at 100 nm/K, 0.01 K of read-out noise is 1 nm of apparent drift).
This module separates the two with the state-space form of the cubic
smoothing spline (Wecker & Ansley, JASA 78(381), 1983; Durbin & Koopman,
*Time Series Analysis by State Space Methods*, 2nd ed., 2012, §3.2 and §7.2):

    C(t_k) = s(t_k) + ε_k,       ε_k ~ N(0, r)           (read-out noise)
    s'' = white noise of spectral density q               (integrated random walk)

i.e. state (s, ds/dt) with transition [[1, Δ], [0, 1]] and process noise
q·[[Δ³/3, Δ²/2], [Δ²/2, Δ]] over a step Δ. Nothing is tuned to an
instrument: the signal-to-noise ratio λ = q/r is estimated from the log
itself by maximum likelihood (r concentrated out of the Gaussian
likelihood, prediction-error decomposition; time in units of the median
sampling interval), on a coarse log grid, then refined by golden-section
search. The smoothed s (the Rauch–Tung–Striebel pass) uses every sample
logged so far, so a time inside the log gets a two-sided estimate and the
last sample the filtered one. Beyond the last sample the quantity is
forecast as the model forecasts it, along the filtered slope there (a
drift model asked about the next frame before its readings arrive). A
channel without read-out noise gets a large λ and comes back (nearly)
unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import numpy.typing as npt

__all__ = ["SmoothedChannel", "smooth_channel"]

FloatArray = npt.NDArray[np.float64]

#: log10 λ searched (λ = q/r per sampling interval³): from a straight line
#: through the noise to no smoothing at all.
_LOG_RATIO_RANGE = (-10.0, 6.0)
_COARSE_POINTS = 17
_GOLDEN_STEPS = 24
#: Initial state variance, relative to the squared data range (diffuse start).
_DIFFUSE = 1e4


@dataclass(frozen=True, slots=True)
class SmoothedChannel:
    """A channel log with its read-out noise removed.

    ``t_s`` (n,) the finite samples' times, ``value`` (n,) the smoothed
    channel there, ``slope_per_s`` its rate of change at the last sample
    (channel units per s), ``noise_sd`` the estimated read-out noise (channel
    units), ``log_ratio`` log10 of the estimated signal-to-noise ratio λ.
    """

    t_s: FloatArray
    value: FloatArray
    slope_per_s: float
    noise_sd: float
    log_ratio: float

    def at(self, t_s: npt.ArrayLike) -> FloatArray:
        """The quantity at ``t_s``: linear between samples, held before the
        first, forecast along :attr:`slope_per_s` after the last."""
        t = np.asarray(t_s, dtype=np.float64)
        if self.t_s.size == 0:
            return np.full(t.shape, np.nan)
        out = np.interp(t, self.t_s, self.value)
        ahead = t - self.t_s[-1]
        return np.asarray(
            np.where(ahead > 0, self.value[-1] + self.slope_per_s * ahead, out), dtype=np.float64
        )


@numba.njit(cache=True)
def _filter(
    tau: FloatArray, z: FloatArray, ratio: float, p0: float, smooth: bool
) -> tuple[float, float, FloatArray]:  # pragma: no cover - numba
    """IRW + white noise Kalman filter with r = 1; optionally the RTS smoother.

    Returns (−2·concentrated log-likelihood, the ML estimate of r, the
    smoothed level and slope (n, 2), or an empty array).
    """
    n = z.size
    xf = np.empty((n, 2))
    pf = np.empty((n, 3))  # p00, p01, p11 of the filtered state
    xp = np.empty((n, 2))
    pp = np.empty((n, 3))
    x0, x1 = z[0], 0.0
    p00, p01, p11 = 1.0, 0.0, p0
    ss = 0.0
    logdet = 0.0
    m = 0
    for i in range(n):
        if i > 0:
            d = tau[i] - tau[i - 1]
            x0 = x0 + d * x1
            a00 = p00 + 2.0 * d * p01 + d * d * p11 + ratio * d * d * d / 3.0
            a01 = p01 + d * p11 + ratio * d * d / 2.0
            a11 = p11 + ratio * d
            p00, p01, p11 = a00, a01, a11
        xp[i, 0], xp[i, 1] = x0, x1
        pp[i, 0], pp[i, 1], pp[i, 2] = p00, p01, p11
        f = p00 + 1.0
        nu = z[i] - x0
        if i >= 2:
            ss += nu * nu / f
            logdet += math.log(f)
            m += 1
        k0, k1 = p00 / f, p01 / f
        x0 += k0 * nu
        x1 += k1 * nu
        p11 = p11 - k1 * p01
        p01 = p01 - k0 * p01
        p00 = p00 - k0 * p00
        xf[i, 0], xf[i, 1] = x0, x1
        pf[i, 0], pf[i, 1], pf[i, 2] = p00, p01, p11
    scale = max(ss / max(m, 1), 1e-300)
    nll = m * math.log(scale) + logdet
    if not smooth:
        return nll, scale, np.empty((0, 2))
    out = np.empty((n, 2))
    s0, s1 = xf[n - 1, 0], xf[n - 1, 1]
    out[n - 1, 0], out[n - 1, 1] = s0, s1
    for i in range(n - 2, -1, -1):
        d = tau[i + 1] - tau[i]
        # J = Pf Fᵀ Pp⁻¹ (2×2), Pp of step i + 1.
        b00 = pf[i, 0] + d * pf[i, 1]
        b01 = pf[i, 1]
        b10 = pf[i, 1] + d * pf[i, 2]
        b11 = pf[i, 2]
        q00, q01, q11 = pp[i + 1, 0], pp[i + 1, 1], pp[i + 1, 2]
        det = q00 * q11 - q01 * q01
        if det <= 0.0:
            det = 1e-300
        i00, i01, i11 = q11 / det, -q01 / det, q00 / det
        j00 = b00 * i00 + b01 * i01
        j01 = b00 * i01 + b01 * i11
        j10 = b10 * i00 + b11 * i01
        j11 = b10 * i01 + b11 * i11
        e0 = s0 - xp[i + 1, 0]
        e1 = s1 - xp[i + 1, 1]
        s0 = xf[i, 0] + j00 * e0 + j01 * e1
        s1 = xf[i, 1] + j10 * e0 + j11 * e1
        out[i, 0], out[i, 1] = s0, s1
    return nll, scale, out


def smooth_channel(t_s: npt.ArrayLike, values: npt.ArrayLike) -> SmoothedChannel:
    """Remove the read-out noise of one channel log (see the module docstring).

    Parameters
    ----------
    t_s : array_like, shape (n,)
        Sample times, s, non-decreasing.
    values : array_like, shape (n,)
        Logged values (any unit); non-finite ones are left out.

    Returns
    -------
    SmoothedChannel
        At the finite samples. With fewer than four of them, or a constant
        log, the values come back unchanged (``noise_sd`` and slope 0).
    """
    t = np.asarray(t_s, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if t.shape != v.shape or t.ndim != 1:
        raise ValueError(f"t_s and values must be 1-D of one length, got {t.shape} and {v.shape}")
    ok = np.isfinite(v) & np.isfinite(t)
    t, v = t[ok], v[ok]
    span = float(np.ptp(v)) if v.size else 0.0
    if v.size < 4 or span == 0.0:
        return SmoothedChannel(t, v.copy(), 0.0, 0.0, math.inf)
    steps = np.diff(t)
    unit = float(np.median(steps[steps > 0])) if np.any(steps > 0) else 1.0
    tau = (t - t[0]) / unit
    z = (v - v[0]) / span  # the ratio does not depend on the unit; keep numbers O(1)
    p0 = _DIFFUSE

    def nll(log_ratio: float) -> float:
        return float(_filter(tau, z, 10.0**log_ratio, p0, False)[0])

    lo, hi = _LOG_RATIO_RANGE
    grid = np.linspace(lo, hi, _COARSE_POINTS)
    values_nll = [nll(g) for g in grid]
    best = int(np.argmin(values_nll))
    a = float(grid[max(best - 1, 0)])
    b = float(grid[min(best + 1, grid.size - 1)])
    # Golden-section search between the best grid point's neighbours.
    g = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = nll(c), nll(d)
    for _ in range(_GOLDEN_STEPS):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = nll(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = nll(d)
    log_ratio, f_best = (c, fc) if fc < fd else (d, fd)
    if values_nll[best] < f_best:
        log_ratio = float(grid[best])
    _, r, state = _filter(tau, z, 10.0**log_ratio, p0, True)
    return SmoothedChannel(
        t_s=t,
        value=v[0] + span * state[:, 0],
        slope_per_s=float(span * state[-1, 1] / unit),
        noise_sd=span * math.sqrt(r),
        log_ratio=float(log_ratio),
    )
