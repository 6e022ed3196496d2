"""Baselines, the Kalman filter's noise estimation, the paper's NN (LM convergence,
determinism), state_dict round trips of every predictor, and the position convention."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from afmdrift.model import (
    PREDICTOR_NAMES,
    History,
    ModelConfig,
    NNConfig,
    Observation,
    commanded_offset_nm,
    drift_from_measurements,
    make_predictor,
    truth_frame_mean,
)
from afmdrift.model._kalman import KalmanPredictor, estimate_noise
from afmdrift.model._synthetic import synthetic_series
from afmdrift.records import Event, EventKind, Frame, ScanDirection

PERIOD_S = 256.0


def _obs(t: float, x: float, y: float, i: int, sigma: float = 0.5) -> Observation:
    return Observation(t, x, y, sigma, ScanDirection.UP, i)


# ---------------------------------------------------------------- positions


def test_commanded_move_is_added_back_to_the_image_position() -> None:
    """A +Δ offset move shifts image content by −Δ; drift = image position + offset."""
    events = [
        Event(1000.0, EventKind.OFFSET_MOVE, 50.0, -20.0),
        Event(1500.0, EventKind.MANIPULATION, 1.0, 1.0),
    ]
    t = np.array([100.0, 900.0, 1100.0, 2000.0])
    drift = np.column_stack([t * 0.01, t * -0.02])
    image = drift - commanded_offset_nm(t, events)
    p = drift_from_measurements(t, image, events)
    np.testing.assert_allclose(p, drift)


def test_reference_frame_after_a_move_still_has_zero_drift() -> None:
    events = [
        Event(0.0, EventKind.OFFSET_MOVE, 100.0, 100.0),
        Event(500.0, EventKind.OFFSET_MOVE, 10.0, 0.0),
    ]
    p = drift_from_measurements([64.0, 600.0], [[0.0, 0.0], [-10.0, 0.0]], events)
    np.testing.assert_allclose(p, [[0.0, 0.0], [0.0, 0.0]])


def test_drift_from_measurements_rejects_mismatched_shapes() -> None:
    with pytest.raises(ValueError, match="3 rows for 2 times"):
        drift_from_measurements([0.0, 1.0], np.zeros((3, 2)), [])


@pytest.mark.parametrize("direction", [ScanDirection.UP, ScanDirection.DOWN])
def test_linear_drift_frame_mean_equals_drift_at_mid_scan(direction: ScanDirection) -> None:
    """Why measurements sit at t_mid: for linear drift the row-mean is p(t_mid)."""
    frame = Frame(3, np.zeros((64, 64)), (1.0, 1.0), 1000.0, 1128.0, direction)
    tt = np.linspace(0, 3000, 3001)
    truth = np.column_stack([0.3 * tt + 2, -0.1 * tt])
    np.testing.assert_allclose(
        truth_frame_mean(frame, tt, truth), [0.3 * frame.t_mid_s + 2, -0.1 * frame.t_mid_s]
    )


# ---------------------------------------------------------------- baselines


def test_last_value_and_constant_velocity() -> None:
    h = History()
    lv, cv = make_predictor("last_value"), make_predictor("constant_velocity")
    for i, (x, y) in enumerate([(0.0, 0.0), (2.0, -1.0)]):
        for p in (lv, cv):
            p.update(_obs(PERIOD_S * i, x, y, i), h)
    np.testing.assert_allclose(lv.predict([2 * PERIOD_S], h).mean_nm, [[2.0, -1.0]])
    np.testing.assert_allclose(cv.predict([2 * PERIOD_S], h).mean_nm, [[4.0, -2.0]])


def test_predict_before_any_update_names_the_predictor() -> None:
    for name in ("last_value", "kalman", "physics"):
        with pytest.raises(ValueError, match=name):
            make_predictor(name).predict([1.0], History())


def test_out_of_order_observation_is_rejected() -> None:
    p = make_predictor("constant_velocity")
    p.update(_obs(100.0, 0, 0, 0), History())
    with pytest.raises(ValueError, match="not after"):
        p.update(_obs(50.0, 0, 0, 1), History())


# ---------------------------------------------------------------- Kalman


def test_kalman_noise_estimates_are_near_the_generating_values() -> None:
    """Maximum-likelihood q and r of a simulated constant-velocity process (frame units)."""
    rng = np.random.default_rng(7)
    q_true, r_true, n = 0.05, 1.0, 400
    v = np.cumsum(rng.normal(0, math.sqrt(q_true), n))
    pos = np.cumsum(v) + rng.normal(0, math.sqrt(q_true / 12), n)
    z = pos + rng.normal(0, math.sqrt(r_true), n)
    q, r = estimate_noise(np.arange(n, dtype=float), z, 2)
    assert q_true / 3 < q < q_true * 3, q
    assert r_true / 2 < r < r_true * 2, r


def test_kalman_tracks_a_constant_velocity_exactly_enough() -> None:
    h = History()
    k = KalmanPredictor()
    rng = np.random.default_rng(1)
    for i in range(40):
        t = PERIOD_S * i
        k.update(_obs(t, 0.05 * t + rng.normal(0, 0.3), -0.02 * t + rng.normal(0, 0.3), i), h)
    pred = k.predict([PERIOD_S * 40], h)
    np.testing.assert_allclose(
        pred.mean_nm[0], [0.05 * PERIOD_S * 40, -0.02 * PERIOD_S * 40], atol=1.0
    )
    assert np.all(pred.sigma_nm > 0)


# ---------------------------------------------------------------- NN


def test_lm_converges_on_a_smooth_function() -> None:
    torch = pytest.importorskip("torch")
    from afmdrift.model._nn import init_weights, lm_fit, mlp

    x = torch.linspace(-2, 2, 40, dtype=torch.float64)[:, None]
    y = torch.sin(1.5 * x) + 0.3 * x**2
    gen = torch.Generator().manual_seed(0)
    theta0 = init_weights(1, 10, 1, gen)
    cost0 = float(((y - mlp(theta0, x, 1, 10, 1)) ** 2).sum())
    _theta, cost, lam = lm_fit(theta0, x, y, shape=(1, 10, 1), iterations=60, damping=1e-2)
    assert cost < 1e-4 * cost0
    assert cost < 1e-3
    assert lam > 0


def test_nn_is_deterministic_for_a_seed() -> None:
    s = synthetic_series(hours=3.0, seed=2)
    cfg = ModelConfig(nn=NNConfig(initial_iterations=30, seed=5))
    preds = []
    for _ in range(2):
        p = make_predictor("nn", cfg)
        for o in s.observations:
            p.update(o, s.history)
        preds.append(p.predict([s.observations[-1].t_s + PERIOD_S], s.history).mean_nm)
    np.testing.assert_array_equal(preds[0], preds[1])


def test_nn_learns_a_periodic_increment_pattern() -> None:
    """The published net, trained by LM, predicts a drift whose increments follow a
    deterministic pattern far better than constant velocity."""
    t = np.arange(60) * PERIOD_S
    inc = 3.0 * np.sin(2 * np.pi * np.arange(60) / 6.0)
    xy = np.column_stack([np.cumsum(inc), -np.cumsum(inc) / 2])
    h = History()
    nn = make_predictor("nn", ModelConfig(nn=NNConfig(channels=[])))
    cv = make_predictor("constant_velocity")
    err_nn, err_cv = [], []
    for i in range(60):
        if i >= 40:
            err_nn.append(abs(nn.predict([t[i]], h).mean_nm[0, 0] - xy[i, 0]))
            err_cv.append(abs(cv.predict([t[i]], h).mean_nm[0, 0] - xy[i, 0]))
        for p in (nn, cv):
            p.update(_obs(float(t[i]), float(xy[i, 0]), float(xy[i, 1]), i), h)
    assert np.mean(err_nn) < 0.2 * np.mean(err_cv)


# ---------------------------------------------------------------- state


@pytest.mark.parametrize("name", PREDICTOR_NAMES)
def test_state_dict_round_trip_through_json(name: str) -> None:
    """A predictor restored from its JSON state predicts and continues exactly as the original."""
    s = synthetic_series(hours=2.5, seed=9)
    cfg = ModelConfig(nn=NNConfig(initial_points=12, initial_iterations=20))
    a = make_predictor(name, cfg)
    obs = s.observations
    for o in obs[:-3]:
        a.update(o, s.history)
    state = json.loads(json.dumps(a.state_dict(), allow_nan=False))
    b = make_predictor(name, cfg)
    b.load_state_dict(state)
    t = [obs[-3].t_s, obs[-1].t_s + 100.0]
    np.testing.assert_allclose(
        b.predict(t, s.history).mean_nm, a.predict(t, s.history).mean_nm, rtol=0, atol=1e-9
    )
    for o in obs[-3:]:
        a.update(o, s.history)
        b.update(o, s.history)
    t2 = [obs[-1].t_s + PERIOD_S]
    np.testing.assert_allclose(
        b.predict(t2, s.history).mean_nm, a.predict(t2, s.history).mean_nm, rtol=0, atol=1e-9
    )


def test_joint_nn_round_trips_and_predicts_both_axes() -> None:
    s = synthetic_series(hours=3.0, seed=6)
    cfg = ModelConfig(nn=NNConfig(joint=True, initial_points=12, initial_iterations=20))
    a = make_predictor("nn", cfg)
    for o in s.observations:
        a.update(o, s.history)
    b = make_predictor("nn", cfg)
    b.load_state_dict(json.loads(json.dumps(a.state_dict())))
    t = [s.observations[-1].t_s + PERIOD_S]
    np.testing.assert_array_equal(a.predict(t, s.history).mean_nm, b.predict(t, s.history).mean_nm)
    assert len(a.state_dict()["net"]["theta"]) == 1


def test_unknown_predictor_name_lists_the_known_ones() -> None:
    from afmdrift.errors import ConfigError

    with pytest.raises(ConfigError, match="known: last_value"):
        make_predictor("oracle")


def test_importing_the_model_package_does_not_import_torch() -> None:
    import subprocess
    import sys

    code = "import sys, afmdrift.model; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_least_squares_equals_the_ordinary_fit_on_a_well_conditioned_design() -> None:
    from afmdrift.model import solve_wls

    rng = np.random.default_rng(5)
    t = np.linspace(0.0, 1.0, 40)
    x = np.column_stack([np.ones_like(t), t, np.sin(6 * t)])
    y = x @ np.array([2.0, -3.0, 0.5]) + rng.normal(0.0, 0.05, t.size)
    w = np.full(t.size, 4.0)
    fit = solve_wls(x, y, w)
    ols, *_ = np.linalg.lstsq(x, y, rcond=None)
    np.testing.assert_allclose(fit.coef, ols, rtol=1e-9, atol=1e-12)


def test_least_squares_leaves_out_a_direction_two_near_alike_columns_span() -> None:
    # A channel that has drifted almost linearly so far, beside a trend: the
    # ordinary fit gives huge opposite coefficients; a frame later, where the
    # channel bends, its prediction would be far off.
    from afmdrift.model import solve_wls

    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 1.0, 14)
    channel = 0.037 - 0.002 * t + 1e-7 * np.sin(40 * t)
    x = np.column_stack([np.ones_like(t), t, channel])
    y = 1.0 + 2.0 * t + rng.normal(0.0, 0.3, t.size)
    w = np.ones_like(t)
    fit = solve_wls(x, y, w)
    ols, *_ = np.linalg.lstsq(x, y, rcond=None)
    assert np.abs(ols).max() > 1e4
    assert np.abs(fit.coef[:2]).max() < 100
    nxt = np.array([1.0, 1.08, 0.037 - 0.002 * 1.08 + 5e-4])  # the channel bends
    assert abs(nxt @ fit.coef - (1.0 + 2.0 * 1.08)) < 2.0
    assert abs(nxt @ ols - (1.0 + 2.0 * 1.08)) > 50.0
