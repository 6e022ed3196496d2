"""Each drift effect shows its documented signature (docs/physics.md) in recorded truth.

Sessions are recorded with tiny frames so the tests stay fast; the signatures are
read from ``truth.csv``, ``truth_components.csv``, ``channels.csv`` and ``events.csv``.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
from scipy import optimize, signal

from afmdrift.drivers import EventKind
from afmdrift.drivers.sim import DriftPhysics, parse_scenario
from afmdrift.drivers.sim._record import record_session
from afmdrift.drivers.sim._scenario import PhysicsConfig
from afmdrift.session import Session, read_session

OFF: dict[str, Any] = {"thermal": {"enabled": False}}


def record(
    tmp_path: Path,
    physics: dict[str, Any],
    *,
    duration_s: float,
    seed: int = 1,
    **extra: Any,
) -> Session:
    data: dict[str, Any] = {
        "scan": {
            "pixels": [16, 16],
            "size_nm": [64.0, 64.0],
            "line_rate_hz": 1.0,
            "frame_period_s": 600.0,
        },
        "sample": {"map_px": 128, "grid_nm": 4.0},
        "physics": physics,
        "sensors": {"record_period_s": 1.0, "truth_period_s": 1.0},
    }
    data.update(extra)
    out = tmp_path / "session"
    record_session(parse_scenario(data), out, seed=seed, duration_s=duration_s)
    return read_session(out)


def components(path: Path) -> dict[str, npt.NDArray[np.float64]]:
    with (path / "truth_components.csv").open() as fh:
        rows = list(csv.reader(fh))
    data = np.array(rows[1:], dtype=np.float64)
    return {name: data[:, k] for k, name in enumerate(rows[0])}


def truth(s: Session) -> tuple[npt.NDArray[np.float64], ...]:
    assert s.truth is not None
    return s.truth[:, 0], s.truth[:, 1], s.truth[:, 2]


@pytest.mark.slow
def test_thermal_drift_lags_head_temperature_by_first_order_response(tmp_path: Path) -> None:
    """dT_s/dt = (T_h - T_s)/tau: for a sine of period P the drift has gain
    1/sqrt(1+(w tau)^2) and lags by atan(w tau)/w (≈ tau when w tau << 1)."""
    period, tau, alpha = 3600.0, 600.0, (80.0, -50.0)
    s = record(
        tmp_path,
        {
            "room": {"ac_amplitude_k": 1.0, "ac_period_s": period},
            "thermal": {"enabled": True, "alpha_nm_per_k": list(alpha), "tau_s": tau},
        },
        duration_s=6 * period,
        sensors={"record_period_s": 1.0, "truth_period_s": 1.0, "temperature_noise_c": 0.01},
    )
    t, x, y = truth(s)
    temp = s.channel_at("temperature_c", t)
    w = 2 * math.pi / period
    keep = t >= 2 * period  # transient over (> 10 tau)
    basis = np.exp(1j * w * t[keep])
    amp_t = np.mean((temp[keep] - temp[keep].mean()) * basis)
    amp_x = np.mean((x[keep] - x[keep].mean()) * basis) / alpha[0]
    amp_y = np.mean((y[keep] - y[keep].mean()) * basis) / alpha[1]
    gain_expected = 1 / math.sqrt(1 + (w * tau) ** 2)
    lag_expected_s = math.atan(w * tau) / w
    for amp in (amp_x, amp_y):
        assert abs(amp) / abs(amp_t) == pytest.approx(gain_expected, rel=0.01)
        lag_s = (np.angle(amp) - np.angle(amp_t)) / w  # basis exp(+iwt)
        assert lag_s == pytest.approx(lag_expected_s, rel=0.02)
    # The same lag is the peak of the cross-correlation of drift and temperature.
    dt = temp[keep] - temp[keep].mean()
    dx = x[keep] - x[keep].mean()
    lags = np.arange(0, 1500)
    xc = [np.dot(dt[: dt.size - k], dx[k:]) for k in lags]
    assert lags[int(np.argmax(xc))] == pytest.approx(lag_expected_s, abs=15.0)


@pytest.mark.slow
def test_ac_cycle_is_the_periodogram_peak_of_the_temperature_channel(tmp_path: Path) -> None:
    period = 1200.0
    s = record(
        tmp_path,
        {
            "room": {
                "ac_amplitude_k": 0.3,
                "ac_period_s": period,
                "ac_shape": "triangle",
                "fluctuation_k": 0.05,
                "fluctuation_tau_s": 300.0,
            },
            "thermal": {"enabled": True, "tau_s": 900.0},
        },
        duration_s=8 * 3600.0,
    )
    f, pxx = signal.periodogram(s.channels["temperature_c"], fs=1.0, detrend="linear")
    peak = f[1 + int(np.argmax(pxx[1:]))]
    assert 1 / peak == pytest.approx(period, rel=0.02)
    # And the drift follows it: the thermal component peaks at the same period.
    assert s.truth is not None
    f2, pxx2 = signal.periodogram(s.truth[:, 1], fs=1.0, detrend="linear")
    assert 1 / f2[1 + int(np.argmax(pxx2[1:]))] == pytest.approx(period, rel=0.02)


def test_warmup_decays_exponentially_with_tau_w(tmp_path: Path) -> None:
    amp, tau_w = (300.0, -120.0), 2400.0
    s = record(
        tmp_path,
        {**OFF, "warmup": {"enabled": True, "amplitude_nm": list(amp), "tau_s": tau_w}},
        duration_s=4 * 3600.0,
    )
    t, x, y = truth(s)

    def model(tt: Any, a: float, tau: float) -> Any:
        return a * (1 - np.exp(-tt / tau))

    (a_x, tau_x), _ = optimize.curve_fit(model, t, x, p0=(100.0, 1000.0))
    (a_y, tau_y), _ = optimize.curve_fit(model, t, y, p0=(-100.0, 1000.0))
    assert (a_x, a_y) == pytest.approx(amp, rel=1e-3)
    assert (tau_x, tau_y) == pytest.approx((tau_w, tau_w), rel=1e-3)
    # Velocity form: log|v| falls linearly with slope -1/tau_w.
    v = np.gradient(x, t)
    slope = np.polyfit(t[10:-10], np.log(np.abs(v[10:-10])), 1)[0]
    assert -1 / slope == pytest.approx(tau_w, rel=0.01)


def test_creep_relaxes_log_linearly_after_an_offset_move(tmp_path: Path) -> None:
    gamma, t0, t_m, delta = 0.04, 2.0, 1000.0, (500.0, -200.0)
    s = record(
        tmp_path,
        {**OFF, "creep": {"enabled": True, "gamma_per_decade": gamma, "t0_s": t0}},
        duration_s=3 * 3600.0,
        offset_moves=[{"t_s": t_m, "x_nm": delta[0], "y_nm": delta[1]}],
    )
    t, x, y = truth(s)
    moves = [e for e in s.events if e.kind is EventKind.OFFSET_MOVE]
    assert [(e.t_s, e.x_nm, e.y_nm) for e in moves] == [(t_m, *delta)]
    assert np.all(x[t <= t_m] == 0.0)
    after = t > t_m
    decades = np.log10(1 + (t[after] - t_m) / t0)
    for axis, d in ((x, delta[0]), (y, delta[1])):
        slope, icpt = np.polyfit(decades, axis[after], 1)
        assert slope == pytest.approx(-gamma * d, rel=1e-6)  # -gamma*Delta per decade
        assert icpt == pytest.approx(0.0, abs=1e-6)


def test_hysteresis_error_depends_on_the_direction_of_approach(tmp_path: Path) -> None:
    r = (5.0, 3.0)
    moves = [
        {"t_s": 100.0, "x_nm": 100.0, "y_nm": 100.0},  # approach 100 from below
        {"t_s": 200.0, "x_nm": 200.0, "y_nm": 200.0},
        {"t_s": 300.0, "x_nm": 100.0, "y_nm": 100.0},  # approach 100 from above
        {"t_s": 400.0, "x_nm": 100.5, "y_nm": 100.5},  # small reversal inside the play
    ]
    s = record(
        tmp_path,
        {**OFF, "hysteresis": {"enabled": True, "play_nm": list(r)}},
        duration_s=600.0,
        offset_moves=moves,
    )
    _, x, y = truth(s)
    # Actual offset a = c - r after increasing moves, c + r after decreasing ones;
    # the drift is -(a - c).
    assert (x[150], y[150]) == pytest.approx(r)
    assert (x[350], y[350]) == pytest.approx((-r[0], -r[1]))
    # Same command (100 nm), opposite histories: the loop is 2r wide.
    assert x[150] - x[350] == pytest.approx(2 * r[0])
    # A reversal smaller than the play leaves the actual position where it was.
    assert (x[450], y[450]) == pytest.approx((-r[0] + 0.5, -r[1] + 0.5))


def test_humidity_drift_is_proportional_to_relative_humidity(tmp_path: Path) -> None:
    beta = (2.5, -1.2)
    s = record(
        tmp_path,
        {
            **OFF,
            "humidity": {
                "enabled": True,
                "amplitude_pct": 6.0,
                "period_s": 7200.0,
                "fluctuation_pct": 1.0,
                "fluctuation_tau_s": 600.0,
                "beta_nm_per_pct": list(beta),
            },
        },
        duration_s=4 * 3600.0,
        sensors={"record_period_s": 1.0, "truth_period_s": 1.0, "humidity_noise_pct": 0.05},
    )
    t, x, y = truth(s)
    rh = s.channel_at("humidity_pct", t)
    for axis, b in ((x, beta[0]), (y, beta[1])):
        slope = np.polyfit(rh, axis, 1)[0]
        assert slope == pytest.approx(b, rel=0.01)
        assert np.corrcoef(rh, axis)[0, 1] ** 2 > 0.99


def test_tip_change_is_a_step_at_the_logged_event(tmp_path: Path) -> None:
    step, t_e = (7.5, -4.0), 1234.0
    s = record(
        tmp_path,
        {
            **OFF,
            "tip_changes": {"enabled": True, "scheduled": [{"t_s": t_e, "step_nm": list(step)}]},
        },
        duration_s=2400.0,
    )
    t, x, y = truth(s)
    tips = [e.t_s for e in s.events if e.kind is EventKind.TIP_CHANGE]
    assert tips == [t_e]
    assert np.all(x[t < t_e] == 0.0)
    assert np.all(x[t > t_e] == step[0])
    assert np.all(y[t > t_e] == step[1])


@pytest.mark.slow
def test_spontaneous_tip_changes_follow_the_configured_rate(tmp_path: Path) -> None:
    s = record(
        tmp_path,
        {**OFF, "tip_changes": {"enabled": True, "rate_per_h": 6.0, "step_sigma_nm": 3.0}},
        duration_s=10 * 3600.0,
    )
    n = sum(e.kind is EventKind.TIP_CHANGE for e in s.events)
    assert 60 - 4 * math.sqrt(60) < n < 60 + 4 * math.sqrt(60)


def test_random_walk_variance_grows_linearly_with_time() -> None:
    sigma = (0.4, 0.2)
    physics = PhysicsConfig.model_validate(
        {**OFF, "random_walk": {"enabled": True, "sigma_nm_per_sqrt_s": list(sigma)}}
    )
    t = np.arange(0.0, 200_000.0, 1.0)
    p = DriftPhysics(physics, seed=9).drift_at(t)
    for lag in (1, 10, 100, 1000):
        inc = p[lag:] - p[:-lag]
        var = inc.var(axis=0)
        assert var[0] / lag == pytest.approx(sigma[0] ** 2, rel=0.15)
        assert var[1] / lag == pytest.approx(sigma[1] ** 2, rel=0.15)


def test_truth_components_sum_to_truth_and_start_at_zero(tmp_path: Path) -> None:
    s = record(
        tmp_path,
        {
            "room": {"ac_amplitude_k": 0.3, "trend_k_per_h": 0.2},
            "thermal": {"enabled": True},
            "warmup": {"enabled": True, "amplitude_nm": [50.0, 20.0]},
            "random_walk": {"enabled": True, "sigma_nm_per_sqrt_s": [0.1, 0.1]},
            "humidity": {"enabled": True, "amplitude_pct": 3.0, "beta_nm_per_pct": [1.0, 1.0]},
        },
        duration_s=3000.0,
    )
    comp = components(tmp_path / "session")
    _, x, y = truth(s)
    sum_x = sum(v for k, v in comp.items() if k.endswith("_x_nm"))
    sum_y = sum(v for k, v in comp.items() if k.endswith("_y_nm"))
    np.testing.assert_allclose(sum_x, x, atol=1e-9)
    np.testing.assert_allclose(sum_y, y, atol=1e-9)
    assert x[0] == 0.0
    assert y[0] == 0.0


def test_creep_of_thousands_of_closed_loop_moves_matches_the_exact_sum() -> None:
    """Guards the O(1)-per-query creep evaluation (sum of exponentials) against the
    exact log law when a controller moves the offset every second."""
    gamma, t0 = 0.03, 1.0
    physics = PhysicsConfig.model_validate(
        {**OFF, "creep": {"enabled": True, "gamma_per_decade": gamma, "t0_s": t0}}
    )
    sim = DriftPhysics(physics, seed=0)
    rng = np.random.default_rng(1)
    offsets = np.cumsum(rng.normal(0.0, 2.0, (3000, 2)), axis=0)
    times = 1.0 + np.arange(3000.0)
    for t_m, (x, y) in zip(times, offsets, strict=True):
        sim.command_offset(float(t_m), float(x), float(y))
    deltas = np.diff(np.vstack([[0.0, 0.0], offsets]), axis=0)
    query = np.array([0.5, 1.0, 1.5, 17.25, 999.9, 2500.0, 3000.0, 86400.0])
    got = sim.components_at(query)["creep"]
    for q, g in zip(query, got, strict=True):
        past = times < q
        decades = np.log10(1 + (q - times[past]) / t0)
        exact = -gamma * (deltas[past] * decades[:, None]).sum(axis=0)
        np.testing.assert_allclose(g, exact, rtol=0, atol=1e-7)


def _first_order(
    t: npt.NDArray[np.float64], u: npt.NDArray[np.float64], tau_s: float
) -> npt.NDArray[np.float64]:
    """τ·dy/dt = u − y from y(0) = u(0), exact for u linear between samples."""
    y = np.empty_like(u)
    y[0] = u[0]
    for k in range(1, t.size):
        a = math.exp(-(t[k] - t[k - 1]) / tau_s)
        slope = (u[k] - u[k - 1]) / (t[k] - t[k - 1])
        y[k] = u[k] - slope * tau_s + a * (y[k - 1] - u[k - 1] + slope * tau_s)
    return y


def test_extra_channel_moves_the_sample_through_its_lagged_paths(tmp_path: Path) -> None:
    paths = [{"gain_nm_per_unit": [8.0, -6.0], "tau_s": 600.0}, {"gain_nm_per_unit": [2.0, 1.0]}]
    channel = {
        "name": "pressure_hpa",
        "mean": 1013.0,
        "amplitude": 2.0,
        "period_s": 5400.0,
        "fluctuation": 0.3,
        "fluctuation_tau_s": 900.0,
        "noise": 0.0,
        "paths": paths,
    }
    s = record(tmp_path, {**OFF, "channels": [channel]}, duration_s=3 * 3600.0)
    t, x, y = truth(s)
    p = s.channel_at("pressure_hpa", t)  # noise 0: the true value, sampled every second
    assert np.ptp(p) > 3.0
    slow = _first_order(t, p, 600.0) - p[0]
    expected_x = 8.0 * slow + 2.0 * (p - p[0])
    expected_y = -6.0 * slow + 1.0 * (p - p[0])
    assert np.max(np.abs(x - expected_x)) < 0.02 * np.ptp(x)
    assert np.max(np.abs(y - expected_y)) < 0.02 * np.ptp(y)
    comps = components(tmp_path / "session")
    np.testing.assert_allclose(comps["channels_x_nm"], x, atol=1e-9)


def test_distractor_channel_is_logged_and_changes_nothing_else(tmp_path: Path) -> None:
    """Regression guard: adding a logged channel must not move the sample or change
    the other random processes of a seed (it draws from its own stream)."""
    physics = {
        "room": {"ac_amplitude_k": 0.5, "fluctuation_k": 0.05},
        "random_walk": {"enabled": True, "sigma_nm_per_sqrt_s": [0.02, 0.02]},
    }
    plain = record(tmp_path / "a", physics, duration_s=3600.0)
    extra = {"name": "laser_power_mw", "mean": 1.5, "fluctuation": 0.03, "noise": 0.002}
    with_d = record(tmp_path / "b", {**physics, "channels": [extra]}, duration_s=3600.0)
    assert plain.truth is not None
    assert with_d.truth is not None
    np.testing.assert_array_equal(plain.truth, with_d.truth)
    np.testing.assert_array_equal(plain.channels["temperature_c"], with_d.channels["temperature_c"])
    assert np.std(with_d.channels["laser_power_mw"]) > 0.005


def test_logged_event_of_any_kind_is_followed_by_its_settling(tmp_path: Path) -> None:
    events = [
        {"t_s": 1000.0, "kind": "stage_move", "amplitude_nm": [20.0, -10.0], "tau_s": 300.0},
        {"t_s": 2500.0, "kind": "door_open", "shape": "none"},
        {"t_s": 3000.0, "kind": "stage_move", "amplitude_nm": [20.0, -10.0], "tau_s": 300.0},
    ]
    s = record(tmp_path, {**OFF, "events": events}, duration_s=4000.0)
    kinds = [(e.t_s, str(e.kind)) for e in s.events if e.kind is not EventKind.POWER_ON]
    assert kinds == [(1000.0, "stage_move"), (2500.0, "door_open"), (3000.0, "stage_move")]
    t, x, y = truth(s)
    resp = sum(np.where(t > t0, -np.expm1(-(t - t0) / 300.0), 0.0) for t0 in (1000.0, 3000.0))
    np.testing.assert_allclose(x, 20.0 * resp, atol=1e-9)
    np.testing.assert_allclose(y, -10.0 * resp, atol=1e-9)


@pytest.mark.parametrize(
    ("physics", "message"),
    [
        ({"channels": [{"name": "temperature_c"}]}, "logged by the simulator already"),
        ({"channels": [{"name": "p_hpa"}, {"name": "p_hpa"}]}, "duplicate channel names"),
        ({"events": [{"t_s": 1.0, "kind": "tip_change"}]}, "simulator's own actions"),
        ({"events": [{"t_s": 1.0, "kind": "Door Open"}]}, "kind"),
    ],
)
def test_bad_extra_channels_and_events_are_config_errors(
    physics: dict[str, Any], message: str
) -> None:
    from afmdrift.errors import ConfigError

    with pytest.raises(ConfigError, match=message):
        parse_scenario({"physics": physics})
