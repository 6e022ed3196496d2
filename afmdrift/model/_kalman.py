"""Kalman-filter drift baseline after Mokaberi & Requicha (2006).

Mokaberi & Requicha, "Towards automatic nanomanipulation: drift compensation
in scanning probe microscopes", IEEE T-ASE 3(3), 2006, track SPM drift with a
Kalman filter on a kinematic state. Each axis is filtered independently with

* ``velocity`` (constant velocity): state (p, v), driven by white acceleration
  noise of spectral density q (nm²/s³ in frame units, see below), or
* ``acceleration`` (constant acceleration): state (p, v, a), driven by white
  jerk noise of density q,

and measurement noise variance r (nm²). Neither is hand-tuned: at every
update (q, r) are re-estimated per axis by maximum likelihood over the most
recent ``window`` points (prediction-error decomposition of the Gaussian
likelihood, evaluated on a log grid of (q, r) for all candidates at once, then
on a finer grid around the best). Time is measured in frame periods (the
median spacing of the observations) so the grid does not depend on the frame
rate. The filter is started diffuse at the first point of the window; the
first ``d`` innovations (d = state dimension) are left out of the likelihood.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from afmdrift.model._base import History, Observation, Prediction
from afmdrift.model._baselines import ObservationLog, _LoggingPredictor, as_times

__all__ = ["KalmanPredictor", "kalman_nll"]

FloatArray = npt.NDArray[np.float64]

_COARSE_LOG_Q = np.arange(-9.0, 4.01, 0.5)
_COARSE_LOG_R = np.arange(-4.0, 4.01, 0.5)
_FINE_STEPS = np.arange(-0.375, 0.3751, 0.125)
_DIFFUSE = 1e2


def _transition(dt: float, dim: int) -> FloatArray:
    if dim == 2:
        return np.array([[1.0, dt], [0.0, 1.0]])
    return np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])


def _process_noise(dt: float, dim: int) -> FloatArray:
    """Q for unit spectral density (white acceleration or white jerk)."""
    if dim == 2:
        return np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return np.array(
        [
            [dt**5 / 20, dt**4 / 8, dt**3 / 6],
            [dt**4 / 8, dt**3 / 3, dt**2 / 2],
            [dt**3 / 6, dt**2 / 2, dt],
        ]
    )


def _run_filter(
    tau: FloatArray, z: FloatArray, q: FloatArray, r: FloatArray, dim: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Filter ``z`` for G parameter pairs at once.

    Returns the final state (G, dim), covariance (G, dim, dim) and the negative
    log-likelihood (G,) of the innovations after the first ``dim``.
    """
    g = q.size
    x = np.zeros((g, dim))
    x[:, 0] = z[0]
    # Weakly informative start: velocity (and acceleration) variance of the
    # order of the squared data range per frame, far above any plausible value.
    scale = _DIFFUSE * (1.0 + float(np.ptp(z)) ** 2)
    p = np.zeros((g, dim, dim))
    p[:, 0, 0] = r
    for k in range(1, dim):
        p[:, k, k] = scale
    nll = np.zeros(g)
    for i in range(1, z.size):
        dt = float(tau[i] - tau[i - 1])
        f = _transition(dt, dim)
        x = x @ f.T
        p = f @ p @ f.T + q[:, None, None] * _process_noise(dt, dim)
        s = np.maximum(p[:, 0, 0] + r, 1e-12)
        nu = z[i] - x[:, 0]
        k_gain = p[:, :, 0] / s[:, None]
        x = x + k_gain * nu[:, None]
        p = p - k_gain[:, :, None] * k_gain[:, None, :] * s[:, None, None]
        p = 0.5 * (p + np.swapaxes(p, 1, 2))
        if i >= dim:
            nll += 0.5 * (np.log(2 * math.pi * s) + nu * nu / s)
    return x, p, nll


def kalman_nll(
    t_s: npt.ArrayLike,
    z_nm: npt.ArrayLike,
    *,
    q: npt.ArrayLike,
    r: npt.ArrayLike,
    motion: Literal["velocity", "acceleration"] = "velocity",
) -> FloatArray:
    """Negative log-likelihood of one axis's series for each (q, r) pair.

    ``t_s`` and ``z_nm`` have shape (n,); ``q`` and ``r`` broadcast to (G,)
    and are in frame-period units (time divided by the median spacing).
    """
    t = np.asarray(t_s, dtype=np.float64)
    step = float(np.median(np.diff(t)))
    qq, rr = np.broadcast_arrays(np.asarray(q, dtype=np.float64), np.asarray(r, dtype=np.float64))
    dim = 2 if motion == "velocity" else 3
    _, _, nll = _run_filter(
        (t - t[0]) / step, np.asarray(z_nm, dtype=np.float64), qq.ravel(), rr.ravel(), dim
    )
    return nll


def estimate_noise(tau: FloatArray, z: FloatArray, dim: int) -> tuple[float, float]:
    """Maximum-likelihood (q, r) on a coarse, then a fine log grid."""
    lq, lr = np.meshgrid(_COARSE_LOG_Q, _COARSE_LOG_R, indexing="ij")
    _, _, nll = _run_filter(tau, z, 10.0 ** lq.ravel(), 10.0 ** lr.ravel(), dim)
    best = int(np.argmin(nll))
    cq, cr = float(lq.ravel()[best]), float(lr.ravel()[best])
    fq, fr = np.meshgrid(cq + _FINE_STEPS, cr + _FINE_STEPS, indexing="ij")
    _, _, nll = _run_filter(tau, z, 10.0 ** fq.ravel(), 10.0 ** fr.ravel(), dim)
    best = int(np.argmin(nll))
    return float(10.0 ** fq.ravel()[best]), float(10.0 ** fr.ravel()[best])


def _finite_or_none(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


class KalmanPredictor(_LoggingPredictor):
    """Per-axis Kalman filter with noise estimated by maximum likelihood.

    Parameters
    ----------
    motion : {"velocity", "acceleration"}
        State model (constant velocity or constant acceleration).
    window : int
        Number of most recent points over which (q, r) are estimated and the
        filter is run.
    """

    name = "kalman"

    def __init__(
        self, *, motion: Literal["velocity", "acceleration"] = "velocity", window: int = 50
    ) -> None:
        super().__init__()
        self.motion: Literal["velocity", "acceleration"] = motion
        self.window = int(window)
        self.dim = 2 if motion == "velocity" else 3
        self.min_points_to_predict = 2
        self.noise: list[tuple[float, float]] = [(math.nan, math.nan)] * 2
        self.state: FloatArray = np.zeros((2, self.dim))
        self.cov: FloatArray = np.zeros((2, self.dim, self.dim))

    def update(self, obs: Observation, history: History) -> None:
        self.log.append(obs, self._one_step_error(obs, history))
        self._refit()

    def _refit(self) -> None:
        n = len(self.log)
        if n < self.dim + 2:
            return
        t = self.log.t()[-self.window :]
        xy = self.log.xy()[-self.window :]
        step = float(np.median(np.diff(t)))
        tau = (t - t[0]) / step
        for axis in range(2):
            q, r = estimate_noise(tau, xy[:, axis], self.dim)
            x, p, _ = _run_filter(tau, xy[:, axis], np.array([q]), np.array([r]), self.dim)
            self.noise[axis] = (q, r)
            self.state[axis] = x[0]
            self.cov[axis] = p[0]

    def predict(self, t_s: npt.ArrayLike, history: History) -> Prediction:
        self._require_data()
        t = as_times(t_s)
        n = len(self.log)
        if n < self.dim + 2:
            # Not enough points to estimate the noise: extrapolate the last two.
            xy = self.log.xy()
            mean = np.repeat(xy[-1:], t.size, axis=0)
            if n >= 2:
                tt = self.log.t()
                mean += (t - tt[-1])[:, None] * ((xy[-1] - xy[-2]) / (tt[-1] - tt[-2]))[None, :]
            return Prediction(t, mean, self.log.horizon_sigma(t, fallback_nm=1.0))
        step = self.log.step_s()
        t_last = self.log.t_s[-1]
        mean = np.zeros((t.size, 2))
        sigma = np.zeros((t.size, 2))
        for i, ti in enumerate(t):
            dt = (ti - t_last) / step
            f = _transition(dt, self.dim)
            qn = _process_noise(abs(dt), self.dim)
            for axis in range(2):
                mean[i, axis] = (f @ self.state[axis])[0]
                p = f @ self.cov[axis] @ f.T + self.noise[axis][0] * qn
                sigma[i, axis] = math.sqrt(max(p[0, 0], 0.0))
        return Prediction(t, mean, sigma)

    def state_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "motion": self.motion,
            "window": self.window,
            "log": self.log.to_dict(),
            "noise": [[_finite_or_none(a), _finite_or_none(b)] for a, b in self.noise],
            "state": self.state.tolist(),
            "cov": self.cov.tolist(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.motion = state["motion"]
        self.window = int(state["window"])
        self.dim = 2 if self.motion == "velocity" else 3
        self.log = ObservationLog.from_dict(state["log"])
        self.noise = [
            (math.nan if a is None else float(a), math.nan if b is None else float(b))
            for a, b in state["noise"]
        ]
        self.state = np.asarray(state["state"], dtype=np.float64).reshape(2, self.dim)
        self.cov = np.asarray(state["cov"], dtype=np.float64).reshape(2, self.dim, self.dim)


class KalmanCAPredictor(KalmanPredictor):
    """:class:`KalmanPredictor` with the constant-acceleration model."""

    name = "kalman_ca"

    def __init__(self, *, window: int = 50) -> None:
        super().__init__(motion="acceleration", window=window)
