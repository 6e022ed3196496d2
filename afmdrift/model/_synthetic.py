"""Drift series with known physics, for tests, benchmarks and documentation.

:func:`synthetic_series` returns frame-rate observations of a drift made of
library effects with chosen parameters, plus white measurement noise and an
optional random-walk velocity, and the exact continuous drift for comparison.
Nothing in the service uses it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from afmdrift.model._base import History, Observation
from afmdrift.records import ChannelSample, Event, EventKind, ScanDirection

__all__ = ["SyntheticSeries", "synthetic_series"]

FloatArray = npt.NDArray[np.float64]


@dataclass(slots=True)
class SyntheticSeries:
    """Observations, the history they come with, and the true drift.

    ``truth(t_s) -> (n, 2)`` is the continuous drift (without the scan-direction
    bias, which is a measurement artefact).
    """

    observations: list[Observation]
    history: History
    truth: Callable[[FloatArray], FloatArray]
    params: dict[str, float] = field(default_factory=dict)

    def history_until(self, t_s: float) -> History:
        """The part of the history logged at or before ``t_s``."""
        h = History()
        for k, tc in enumerate(self.history.channel_t_s):
            if tc > t_s:
                break
            h.add_channels(ChannelSample(tc, {n: v[k] for n, v in self.history.channels.items()}))
        h.add_events([e for e in self.history.events if e.t_s <= t_s])
        return h


def synthetic_series(
    *,
    hours: float = 8.0,
    frame_period_s: float = 256.0,
    velocity_nm_per_h: tuple[float, float] = (6.0, -4.0),
    thermal_nm_per_k: tuple[float, float] = (25.0, 12.0),
    thermal_tau_s: float = 1500.0,
    temperature_amplitude_k: float = 0.6,
    temperature_period_s: float = 4.0 * 3600.0,
    creep_fraction: float = 0.08,
    creep_t0_s: float = 20.0,
    moves: tuple[tuple[float, float, float], ...] = ((5000.0, 200.0, -120.0),),
    scan_bias_nm: tuple[float, float] = (0.0, 1.5),
    alternate_directions: bool = True,
    noise_nm: float = 0.5,
    velocity_walk_nm_per_h: float = 0.0,
    seed: int = 0,
    channel_period_s: float = 10.0,
) -> SyntheticSeries:
    """A drift series with trend, lagged thermal expansion, creep and scan bias.

    Parameters
    ----------
    hours : float
        Duration.
    frame_period_s : float
        Time between measurements (each placed at its frame's mid-scan time).
    velocity_nm_per_h : (float, float)
        Constant drift velocity.
    thermal_nm_per_k, thermal_tau_s :
        Expansion coefficient (nm/K) and lag of the scanner behind the logged
        temperature (s).
    temperature_amplitude_k, temperature_period_s :
        Logged temperature: 22 °C + amplitude·sin(2πt/period).
    creep_fraction, creep_t0_s :
        Creep c and t₀ after each move (see the ``creep`` term).
    moves : tuple of (t_s, dx_nm, dy_nm)
        Commanded offset moves (logged as events).
    scan_bias_nm : (float, float)
        Up-minus-down bias of the measured position.
    noise_nm : float
        White measurement noise, per coordinate.
    velocity_walk_nm_per_h : float
        Standard deviation of the per-frame random-walk change of the velocity.
    seed : int
        Random seed.
    """
    rng = np.random.default_rng(seed)
    duration = hours * 3600.0
    t_obs = np.arange(frame_period_s / 2, duration, frame_period_s)
    t_ch = np.arange(0.0, duration + frame_period_s, channel_period_s)
    temp = 22.0 + temperature_amplitude_k * np.sin(2 * np.pi * t_ch / temperature_period_s)
    lag = _lagged_temperature(temp, channel_period_s=channel_period_s, thermal_tau_s=thermal_tau_s)
    walk = _velocity_walk(
        rng, t_obs.size, sigma_nm_per_h=velocity_walk_nm_per_h, frame_period_s=frame_period_s
    )
    drift = _DriftTruth(
        v_nm_per_s=np.asarray(velocity_nm_per_h) / 3600.0,
        thermal_nm_per_k=np.asarray(thermal_nm_per_k),
        t_ch_s=t_ch,
        lag_k=lag,
        moves=moves,
        creep_fraction=creep_fraction,
        creep_t0_s=creep_t0_s,
        t_obs_s=t_obs,
        walk_nm=walk,
    )
    p_obs = drift.at(t_obs)
    p_obs = p_obs - p_obs[0]
    history = _logged_history(t_ch, temp, moves)
    observations = _observations(
        t_obs, p_obs, rng, bias_nm=scan_bias_nm, alternate=alternate_directions, noise_nm=noise_nm
    )
    return SyntheticSeries(
        observations,
        history,
        drift.relative_to(t_obs[:1]),
        {
            "thermal_tau_s": thermal_tau_s,
            "creep_t0_s": creep_t0_s,
            "creep_fraction": creep_fraction,
        },
    )


def _lagged_temperature(
    temp_c: FloatArray, *, channel_period_s: float, thermal_tau_s: float
) -> FloatArray:
    """First-order lag of the logged temperature, relative to its first sample.

    Exact for the sampled (piecewise-linear) temperature on the fine channel
    grid: lag_k = a·lag_{k−1} + (1 − a)·T_k with a = exp(−Δt/τ).

    Parameters
    ----------
    temp_c : ndarray, shape (m,)
        Temperature at the channel times, °C.
    channel_period_s : float
        Channel sampling interval Δt, s.
    thermal_tau_s : float
        Lag τ of the scanner behind the logged temperature, s.

    Returns
    -------
    ndarray, shape (m,)
        Lagged temperature minus ``temp_c[0]``, K.
    """
    a = np.exp(-channel_period_s / thermal_tau_s)
    lag = np.empty_like(temp_c)
    lag[0] = temp_c[0]
    for k in range(1, temp_c.size):
        lag[k] = a * lag[k - 1] + (1 - a) * temp_c[k]
    lag -= temp_c[0]
    return lag


def _velocity_walk(
    rng: np.random.Generator,
    n_frames: int,
    *,
    sigma_nm_per_h: float,
    frame_period_s: float,
) -> FloatArray | None:
    """Position offset of a random-walk velocity at each frame, shape (n, 2), nm.

    ``sigma_nm_per_h`` is the standard deviation of the per-frame velocity
    change. None, and nothing drawn from ``rng``, when it is not positive (so
    the measurement noise drawn afterwards stays the same).
    """
    if sigma_nm_per_h > 0:
        steps = rng.normal(0.0, sigma_nm_per_h / 3600.0, size=(n_frames, 2))
        vel = np.cumsum(steps, axis=0)
        return np.asarray(np.cumsum(vel * frame_period_s, axis=0), dtype=np.float64)
    return None


@dataclass(frozen=True, slots=True)
class _DriftTruth:
    """The continuous drift: trend, lagged thermal expansion, creep, velocity walk.

    Attributes
    ----------
    v_nm_per_s : ndarray, shape (2,)
        Constant drift velocity, nm/s.
    thermal_nm_per_k : ndarray, shape (2,)
        Expansion coefficient, nm/K.
    t_ch_s, lag_k : ndarray, shape (m,)
        Channel times (s) and lagged temperature change at them (K).
    moves : tuple of (t_s, dx_nm, dy_nm)
        Commanded offset moves, each followed by creep.
    creep_fraction, creep_t0_s : float
        Creep c and t₀ (s).
    t_obs_s : ndarray, shape (n,)
        Frame times, s.
    walk_nm : ndarray, shape (n, 2), or None
        Random-walk position offset at the frame times, nm; None without walk.
    """

    v_nm_per_s: FloatArray
    thermal_nm_per_k: FloatArray
    t_ch_s: FloatArray
    lag_k: FloatArray
    moves: tuple[tuple[float, float, float], ...]
    creep_fraction: float
    creep_t0_s: float
    t_obs_s: FloatArray
    walk_nm: FloatArray | None

    def at(self, t_s: FloatArray) -> FloatArray:
        """Drift at times ``t_s`` (scalar or (q,)), shape (q, 2), nm."""
        v, kt = self.v_nm_per_s, self.thermal_nm_per_k
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        p = t[:, None] * v[None, :] + np.interp(t, self.t_ch_s, self.lag_k)[:, None] * kt[None, :]
        for tm, dx, dy in self.moves:
            dt = t - tm
            on = dt > 0
            c = np.zeros_like(t)
            c[on] = self.creep_fraction * np.log10(1 + dt[on] / self.creep_t0_s)
            p += c[:, None] * np.array([dx, dy])[None, :]
        if self.walk_nm is not None:
            p[:, 0] += np.interp(t, self.t_obs_s, self.walk_nm[:, 0])
            p[:, 1] += np.interp(t, self.t_obs_s, self.walk_nm[:, 1])
        return np.asarray(p, dtype=np.float64)

    def relative_to(self, t_ref_s: FloatArray) -> Callable[[FloatArray], FloatArray]:
        """The drift minus its value at ``t_ref_s[0]`` (the reference frame), as a function."""
        ref = self.at(t_ref_s)[0]

        def truth_rel(t_s: FloatArray) -> FloatArray:
            return np.asarray(self.at(t_s) - ref, dtype=np.float64)

        return truth_rel


def _logged_history(
    t_ch_s: FloatArray, temp_c: FloatArray, moves: tuple[tuple[float, float, float], ...]
) -> History:
    """The history the run logs: temperature samples and one event per offset move."""
    history = History()
    for tc, tv in zip(t_ch_s, temp_c, strict=True):
        history.add_channels(ChannelSample(float(tc), {"temperature_c": float(tv)}))
    history.add_events(
        [Event(float(tm), EventKind.OFFSET_MOVE, float(dx), float(dy)) for tm, dx, dy in moves]
    )
    return history


def _observations(
    t_obs_s: FloatArray,
    p_obs_nm: FloatArray,
    rng: np.random.Generator,
    *,
    bias_nm: tuple[float, float],
    alternate: bool,
    noise_nm: float,
) -> list[Observation]:
    """Measured positions: drift ± half the scan bias plus white noise, per frame.

    Parameters
    ----------
    t_obs_s : ndarray, shape (n,)
        Frame times, s.
    p_obs_nm : ndarray, shape (n, 2)
        True drift at the frame times, nm.
    rng : numpy.random.Generator
        Source of the noise (two draws per frame, in frame order).
    bias_nm : (float, float)
        Up-minus-down bias of the measured position, nm.
    alternate : bool
        Frames alternate up, down, up, …; otherwise all are up.
    noise_nm : float
        White measurement noise, per coordinate, nm.
    """
    observations = []
    bias = np.asarray(bias_nm)
    for i, t in enumerate(t_obs_s):
        up = (i % 2 == 0) or not alternate
        meas = p_obs_nm[i] + (0.5 if up else -0.5) * bias + rng.normal(0.0, noise_nm, size=2)
        observations.append(
            Observation(
                t_s=float(t),
                x_nm=float(meas[0]),
                y_nm=float(meas[1]),
                sigma_nm=noise_nm,
                direction=ScanDirection.UP if up else ScanDirection.DOWN,
                frame=i,
            )
        )
    return observations
