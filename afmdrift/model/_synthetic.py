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
    # Exact first-order lag of the sampled (piecewise-linear) temperature on a fine grid.
    a = np.exp(-channel_period_s / thermal_tau_s)
    lag = np.empty_like(temp)
    lag[0] = temp[0]
    for k in range(1, temp.size):
        lag[k] = a * lag[k - 1] + (1 - a) * temp[k]
    lag -= temp[0]
    walk = np.zeros((t_obs.size, 2))
    if velocity_walk_nm_per_h > 0:
        steps = rng.normal(0.0, velocity_walk_nm_per_h / 3600.0, size=(t_obs.size, 2))
        vel = np.cumsum(steps, axis=0)
        walk = np.cumsum(vel * frame_period_s, axis=0)
    v = np.asarray(velocity_nm_per_h) / 3600.0
    kt = np.asarray(thermal_nm_per_k)

    def truth(t_s: FloatArray) -> FloatArray:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        p = t[:, None] * v[None, :] + np.interp(t, t_ch, lag)[:, None] * kt[None, :]
        for tm, dx, dy in moves:
            dt = t - tm
            on = dt > 0
            c = np.zeros_like(t)
            c[on] = creep_fraction * np.log10(1 + dt[on] / creep_t0_s)
            p += c[:, None] * np.array([dx, dy])[None, :]
        if velocity_walk_nm_per_h > 0:
            p[:, 0] += np.interp(t, t_obs, walk[:, 0])
            p[:, 1] += np.interp(t, t_obs, walk[:, 1])
        return np.asarray(p, dtype=np.float64)

    p_obs = truth(t_obs)
    p_obs = p_obs - p_obs[0]
    history = History()
    for tc, tv in zip(t_ch, temp, strict=True):
        history.add_channels(ChannelSample(float(tc), {"temperature_c": float(tv)}))
    history.add_events(
        [Event(float(tm), EventKind.OFFSET_MOVE, float(dx), float(dy)) for tm, dx, dy in moves]
    )
    observations = []
    bias = np.asarray(scan_bias_nm)
    for i, t in enumerate(t_obs):
        up = (i % 2 == 0) or not alternate_directions
        meas = p_obs[i] + (0.5 if up else -0.5) * bias + rng.normal(0.0, noise_nm, size=2)
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
    ref = truth(t_obs[:1])[0]

    def truth_rel(t_s: FloatArray) -> FloatArray:
        return np.asarray(truth(t_s) - ref, dtype=np.float64)

    return SyntheticSeries(
        observations,
        history,
        truth_rel,
        {
            "thermal_tau_s": thermal_tau_s,
            "creep_t0_s": creep_t0_s,
            "creep_fraction": creep_fraction,
        },
    )
