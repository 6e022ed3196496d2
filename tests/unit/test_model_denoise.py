"""The channel read-out noise filter: on a smooth quantity read with white noise it
recovers the quantity and the noise level; a clean channel passes unchanged; the
physics model's channel terms respond to the quantity, not to the noise."""

from __future__ import annotations

import numpy as np
import pytest

from afmdrift.model import History, Observation, PhysicsConfig, PhysicsPredictor
from afmdrift.model._denoise import smooth_channel
from afmdrift.records import ChannelSample

STEP_S = 10.0
PERIOD_S = 256.0


def _room(t_s: np.ndarray) -> np.ndarray:
    """A smooth room temperature, K: a slow ramp and a 40 min air-conditioning swing."""
    return 22.0 + 0.3 * t_s / 28800.0 + 0.2 * np.sin(2 * np.pi * t_s / 2400.0)


def test_noise_removed_and_its_level_estimated() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 8 * 3600.0, STEP_S)
    true = _room(t)
    logged = true + rng.normal(0.0, 0.01, t.size)
    out = smooth_channel(t, logged)
    assert out.noise_sd == pytest.approx(0.01, rel=0.15)
    # The error of the estimate is a small fraction of the read-out noise.
    assert np.sqrt(np.mean((out.value - true) ** 2)) < 0.4 * 0.01


def test_clean_channel_passes_unchanged() -> None:
    t = np.arange(0.0, 8 * 3600.0, STEP_S)
    out = smooth_channel(t, _room(t))
    assert np.max(np.abs(out.value - _room(t))) < 1e-4


def test_short_constant_and_non_finite_logs() -> None:
    out = smooth_channel([0.0, 10.0, 20.0], [1.0, 2.0, 1.5])
    np.testing.assert_array_equal(out.value, [1.0, 2.0, 1.5])
    assert smooth_channel(np.arange(10.0), np.full(10, 3.0)).noise_sd == 0.0
    v = np.sin(np.arange(50.0) / 5.0)
    v[[3, 17]] = np.nan
    out = smooth_channel(np.arange(50.0), v)
    assert out.t_s.size == 48
    assert np.all(np.isfinite(out.value))
    with pytest.raises(ValueError, match=r"\(3,\) and \(2,\)"):
        smooth_channel([0.0, 1.0, 2.0], [0.0, 1.0])


def test_direct_thermal_response_predicted_through_sensor_noise() -> None:
    """Regression (issue 28): a drift that follows the room temperature directly,
    logged by a sensor with 0.01 K of read-out noise at 100 nm/K. Taken at face
    value, every reading passed about 1 nm of noise into the prediction, and the
    default model's ``thermal_lag`` could not go below a 60 s lag, which lags
    where the temperature changes fastest; the one-step error came in bursts
    of several nm."""
    rng = np.random.default_rng(2)
    t_ch = np.arange(0.0, 8 * 3600.0, STEP_S)
    logged = _room(t_ch) + rng.normal(0.0, 0.01, t_ch.size)
    history = History()
    for t, v in zip(t_ch, logged, strict=True):
        history.add_channels(ChannelSample(t_s=float(t), values={"temperature_c": float(v)}))
    model = PhysicsPredictor(PhysicsConfig())  # the default terms
    errors = []
    for i, t in enumerate(np.arange(64.0, 8 * 3600.0 - 200.0, PERIOD_S)):
        p = 100.0 * (_room(np.array([t]))[0] - 22.0) + 5.0 * t / 3600.0
        if i >= 20:
            errors.append(model.predict([t], history).mean_nm[0, 0] - p)
        model.update(Observation(t_s=float(t), x_nm=p, y_nm=0.0, sigma_nm=0.1), history)
    e = np.abs(np.asarray(errors))
    assert model.params["thermal_lag"]["tau_s"] < 30.0
    assert e.mean() < 0.3, e.mean()
    assert e.max() < 1.0, e.max()


def test_forecast_beyond_the_log_follows_the_slope() -> None:
    """Beyond the last reading the quantity goes on along its slope (the next
    frame and the d(t) curve ahead), where the raw log is held flat."""
    t = np.arange(0.0, 3600.0, STEP_S)
    out = smooth_channel(t, 20.0 + 1e-4 * t)
    assert out.slope_per_s == pytest.approx(1e-4, rel=1e-3)
    assert out.at([t[-1] + 600.0])[0] == pytest.approx(20.0 + 1e-4 * (t[-1] + 600.0), abs=1e-4)
    assert out.at([-100.0])[0] == pytest.approx(20.0, abs=1e-4)
