"""Shared observation log and the two trivial baselines.

``last_value`` predicts that the sample stays where it was last measured;
``constant_velocity`` extrapolates the last two measurements linearly. Both
report as uncertainty the RMS of their own past one-step errors (scaled with
the prediction horizon), so every predictor's ``sigma_nm`` is comparable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.model._base import History, Observation, Prediction, Predictor, scan_samples
from afmdrift.records import ScanDirection

__all__ = ["ConstantVelocityPredictor", "LastValuePredictor", "ObservationLog"]

FloatArray = npt.NDArray[np.float64]


@dataclass(slots=True)
class ObservationLog:
    """All observations a predictor has seen, as growing lists.

    ``errors`` holds the one-step prediction error of the owning predictor at
    each observation (NaN where it made none), used for its ``sigma_nm``.
    """

    t_s: list[float] = field(default_factory=list)
    xy_nm: list[tuple[float, float]] = field(default_factory=list)
    sigma_nm: list[float] = field(default_factory=list)
    scan_sign: list[float] = field(default_factory=list)
    errors: list[tuple[float, float]] = field(default_factory=list)
    #: +1/−1: scan direction of the session reference the positions are
    #: measured against (the latest observation that named one); None: unknown.
    ref_sign: float | None = None
    #: Scan window each position averages over, (NaN, NaN) for a point.
    windows: list[tuple[float, float]] = field(default_factory=list)

    def append(self, obs: Observation, error: tuple[float, float] | None = None) -> None:
        if not (math.isfinite(obs.t_s) and math.isfinite(obs.x_nm) and math.isfinite(obs.y_nm)):
            raise ValueError(f"observation of frame {obs.frame} is not finite: {obs!r}")
        if self.t_s and obs.t_s <= self.t_s[-1]:
            raise ValueError(
                f"observation of frame {obs.frame} at t={obs.t_s} s is not after the "
                f"previous one ({self.t_s[-1]} s)"
            )
        self.t_s.append(float(obs.t_s))
        self.xy_nm.append((float(obs.x_nm), float(obs.y_nm)))
        self.sigma_nm.append(float(obs.sigma_nm) if math.isfinite(obs.sigma_nm) else 0.0)
        self.scan_sign.append(1.0 if obs.direction is ScanDirection.UP else -1.0)
        self.errors.append(error if error is not None else (math.nan, math.nan))
        self.windows.append(
            (math.nan, math.nan)
            if obs.window_s is None
            else (float(obs.window_s[0]), float(obs.window_s[1]))
        )
        if obs.reference_direction is not None:
            self.ref_sign = 1.0 if obs.reference_direction is ScanDirection.UP else -1.0

    def __len__(self) -> int:
        return len(self.t_s)

    def t(self) -> FloatArray:
        return np.asarray(self.t_s, dtype=np.float64)

    def xy(self) -> FloatArray:
        return np.asarray(self.xy_nm, dtype=np.float64).reshape(-1, 2)

    def samples(self) -> FloatArray:
        """Times at which a model is averaged to fit each position, (n, m)
        (:func:`~afmdrift.model._base.scan_samples`)."""
        w = np.asarray(self.windows, dtype=np.float64).reshape(-1, 2)
        if w.shape[0] != len(self.t_s):  # a log restored from before windows
            w = np.full((len(self.t_s), 2), np.nan)
        return scan_samples(self.t(), w)

    def step_s(self) -> float:
        """Median spacing between observations (the frame period), s."""
        if len(self.t_s) < 2:
            return math.nan
        return float(np.median(np.diff(self.t())))

    def error_rms(self, *, window: int = 50) -> FloatArray:
        """RMS of the recent finite one-step errors per axis, shape (2,) (NaN if none)."""
        e = np.asarray(self.errors[-window:], dtype=np.float64).reshape(-1, 2)
        e = e[np.all(np.isfinite(e), axis=1)]
        if e.shape[0] == 0:
            return np.full(2, np.nan)
        return np.asarray(np.sqrt(np.mean(e**2, axis=0)), dtype=np.float64)

    def horizon_sigma(self, t_s: FloatArray, *, fallback_nm: float) -> FloatArray:
        """One-step error RMS scaled by (horizon / frame period), shape (n, 2)."""
        rms = self.error_rms()
        if not np.all(np.isfinite(rms)):
            rms = np.full(2, max(fallback_nm, 1e-3))
        step = self.step_s()
        if not math.isfinite(step) or step <= 0:
            scale = np.ones_like(t_s)
        else:
            scale = np.maximum(np.abs(t_s - self.t_s[-1]) / step, 0.0)
            scale = np.maximum(scale, 1e-3)
        return np.asarray(scale[:, None] * rms[None, :], dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {
            "t_s": list(self.t_s),
            "xy_nm": [list(p) for p in self.xy_nm],
            "sigma_nm": list(self.sigma_nm),
            "scan_sign": list(self.scan_sign),
            "errors": [[_json_float(a), _json_float(b)] for a, b in self.errors],
            "ref_sign": self.ref_sign,
            "windows": [[_json_float(a), _json_float(b)] for a, b in self.windows],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ObservationLog:
        return cls(
            t_s=[float(v) for v in d["t_s"]],
            xy_nm=[(float(a), float(b)) for a, b in d["xy_nm"]],
            sigma_nm=[float(v) for v in d["sigma_nm"]],
            scan_sign=[float(v) for v in d["scan_sign"]],
            errors=[(_from_json_float(a), _from_json_float(b)) for a, b in d["errors"]],
            ref_sign=None if d.get("ref_sign") is None else float(d["ref_sign"]),
            windows=[(_from_json_float(a), _from_json_float(b)) for a, b in d.get("windows", [])],
        )


def _json_float(v: float) -> float | None:
    return None if not math.isfinite(v) else float(v)


def _from_json_float(v: float | None) -> float:
    return math.nan if v is None else float(v)


def as_times(t_s: npt.ArrayLike) -> FloatArray:
    """Validate query times into a finite 1-D float array."""
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64)).ravel()
    if not np.all(np.isfinite(t)):
        raise ValueError(f"prediction times must be finite, got {t[~np.isfinite(t)][:3]}")
    return t


class _LoggingPredictor(Predictor):
    """Base for predictors that score their own one-step errors as they go."""

    def __init__(self) -> None:
        self.log = ObservationLog()

    def _one_step_error(self, obs: Observation, history: History) -> tuple[float, float] | None:
        if len(self.log) < self.min_points_to_predict:
            return None
        pred, _ = self.predict_observation(obs, history)
        return (obs.x_nm - float(pred[0]), obs.y_nm - float(pred[1]))

    def observed(self) -> tuple[FloatArray, FloatArray]:
        return self.log.t(), self.log.xy()

    #: Observations needed before predictions are the model's own (not a fallback).
    min_points_to_predict: int = 1

    def _require_data(self) -> None:
        if len(self.log) == 0:
            raise ValueError(f"predictor {self.name!r} has no observations yet; call update first")


class LastValuePredictor(_LoggingPredictor):
    """p̂(t) = p(t_last): the sample is assumed to stay put."""

    name = "last_value"

    def update(self, obs: Observation, history: History) -> None:
        self.log.append(obs, self._one_step_error(obs, history))

    def predict(self, t_s: npt.ArrayLike, history: History) -> Prediction:
        self._require_data()
        t = as_times(t_s)
        mean = np.repeat(self.log.xy()[-1:], t.size, axis=0)
        return Prediction(t, mean, self.log.horizon_sigma(t, fallback_nm=self.log.sigma_nm[-1]))

    def state_dict(self) -> dict[str, Any]:
        return {"name": self.name, "log": self.log.to_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.log = ObservationLog.from_dict(state["log"])


class ConstantVelocityPredictor(_LoggingPredictor):
    """p̂(t) = p_n + (p_n − p_{n−1})·(t − t_n)/(t_n − t_{n−1}).

    With a single observation it predicts that value.
    """

    name = "constant_velocity"
    min_points_to_predict = 2

    def update(self, obs: Observation, history: History) -> None:
        self.log.append(obs, self._one_step_error(obs, history))

    def predict(self, t_s: npt.ArrayLike, history: History) -> Prediction:
        self._require_data()
        t = as_times(t_s)
        xy = self.log.xy()
        mean = np.repeat(xy[-1:], t.size, axis=0)
        if len(self.log) >= 2:
            t_arr = self.log.t()
            v = (xy[-1] - xy[-2]) / (t_arr[-1] - t_arr[-2])
            mean = mean + (t - t_arr[-1])[:, None] * v[None, :]
        return Prediction(t, mean, self.log.horizon_sigma(t, fallback_nm=self.log.sigma_nm[-1]))

    def state_dict(self) -> dict[str, Any]:
        return {"name": self.name, "log": self.log.to_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.log = ObservationLog.from_dict(state["log"])
