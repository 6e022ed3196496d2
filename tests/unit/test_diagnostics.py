"""Diagnostics statistics on synthetic series with known ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmdrift.diagnostics import DiagnoseOptions, RunData, Thresholds, diagnose
from afmdrift.diagnostics._diagnose import MIN_DIAGNOSE_FRAMES
from afmdrift.diagnostics._regression import cv_folds, forecast_comparison
from afmdrift.diagnostics._stats import (
    cusum,
    error_summary,
    find_episodes,
    ljung_box,
    lomb_scargle,
    robust_z,
)
from afmdrift.errors import ConfigError, InputError, TooFewFramesError
from afmdrift.model import PhysicsConfig, PhysicsPredictor
from afmdrift.records import ChannelSample, Event, EventKind


def test_error_summary_of_known_errors() -> None:
    e = np.array([[3.0, 4.0], [0.0, 0.0], [np.nan, 1.0], [-6.0, 8.0]])
    s = error_summary(e)
    assert s["n"] == 3
    assert s["mean_abs_nm"] == pytest.approx(5.0)
    assert s["peak_nm"] == pytest.approx(10.0)
    assert s["rmse_nm"] == pytest.approx(math.sqrt((25 + 0 + 100) / 3))
    assert s["rmse_x_nm"] == pytest.approx(math.sqrt((9 + 36) / 3))


def test_ljung_box_separates_white_noise_from_ar1() -> None:
    rng = np.random.default_rng(1)
    white = rng.normal(size=200)
    ar = np.zeros(200)
    for k in range(1, 200):
        ar[k] = 0.8 * ar[k - 1] + rng.normal()
    _, p_white, lags = ljung_box(white)
    _, p_ar, _ = ljung_box(ar)
    assert lags == 10
    assert p_white > 0.01
    assert p_ar < 1e-6


def test_lomb_scargle_finds_the_period_of_uneven_samples() -> None:
    rng = np.random.default_rng(2)
    t = np.sort(rng.uniform(0, 30000, 150))
    e = np.sin(2 * np.pi * t / 3600.0) + 0.2 * rng.normal(size=t.size)
    period, power = lomb_scargle(t, e)
    assert period[np.argmax(power)] == pytest.approx(3600.0, rel=0.05)
    assert power.max() > 0.8


def test_cusum_locates_a_mean_shift() -> None:
    rng = np.random.default_rng(3)
    z = rng.normal(size=120)
    z[70:] += 2.0
    _, _, segments = cusum(z)
    assert segments, "a 2σ shift over 50 samples must raise an alarm"
    start, stop = segments[0]
    assert 60 <= start <= 75
    assert stop > start


def test_cusum_quiet_on_white_noise() -> None:
    z = np.random.default_rng(4).normal(size=120)
    assert cusum(z)[2] == []


def test_robust_z_ignores_a_single_outlier() -> None:
    x = np.r_[np.random.default_rng(5).normal(size=50), 100.0]
    z = robust_z(x)
    assert z[-1] > 30
    assert np.all(np.abs(z[:-1]) < 5)


def test_cv_folds_spread_contiguous_blocks_over_the_record() -> None:
    labels = cv_folds(100, 5)
    for f in range(5):
        rows = np.flatnonzero(labels == f)
        assert rows.min() <= 20  # every fold spans the record
        assert rows.max() >= 75
    assert np.all(labels[:5] == 0)  # blocks are contiguous


def _frames(n: int = 100, period_s: float = 300.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = 16.0 + period_s * np.arange(n)
    sign = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    return t, t + 16.0, sign


def test_episode_after_an_offset_move_names_the_move() -> None:
    t, _, sign = _frames(60)
    rng = np.random.default_rng(6)
    e = rng.normal(0, 0.5, (60, 2))
    e[30] = [9.0, -7.0]  # the frame right after the move
    move = Event(t_s=float(t[30] - 100.0), kind=EventKind.OFFSET_MOVE, x_nm=80.0, y_nm=-60.0)
    data = RunData.from_arrays(t_s=t, xy_nm=np.zeros((60, 2)), events=[move])
    eps = find_episodes(data, t, np.arange(60), e, sign)
    assert len(eps) == 1
    assert eps[0].t_start_s == t[30]
    assert "offset_move" in eps[0].context
    assert "offset move of (+80, -60) nm" in eps[0].note


def test_episode_in_a_closed_loop_sums_its_moves_in_one_note() -> None:
    """A closed loop moves every few seconds: one note for all of them, not one each."""
    t, _, sign = _frames(60)
    rng = np.random.default_rng(6)
    e = rng.normal(0, 0.5, (60, 2))
    e[30] = [9.0, -7.0]
    moves = [
        Event(t_s=float(t[28] + 5.0 * k), kind=EventKind.OFFSET_MOVE, x_nm=0.5, y_nm=-0.25)
        for k in range(100)
    ]
    data = RunData.from_arrays(t_s=t, xy_nm=np.zeros((60, 2)), events=moves)
    (ep,) = find_episodes(data, t, np.arange(60), e, sign)
    assert "offset moves (a closed loop?) adding up to" in ep.note
    assert "offset move of" not in ep.note
    assert len(ep.note) < 300


def _lagged(t: np.ndarray, temp: np.ndarray, tau_s: float) -> np.ndarray:
    out = np.empty_like(temp)
    out[0] = temp[0]
    for k in range(1, t.size):
        a = math.exp(-(t[k] - t[k - 1]) / tau_s)
        out[k] = a * out[k - 1] + (1 - a) * temp[k]
    return out - temp[0]


def _synthetic(*, humidity_nm_per_pct: float, seed: int, n: int = 90) -> tuple[RunData, np.ndarray]:
    """Thermal lag (τ = 1500 s) + optional humidity coupling + random walk + noise.

    Built here from the equations, independently of the simulator.
    """
    rng = np.random.default_rng(seed)
    tc = np.arange(0.0, 300.0 * n + 600.0, 30.0)
    temp = 22.0 + 0.4 * np.sin(2 * np.pi * tc / 3600.0) + rng.normal(0, 0.003, tc.size)
    rh = 45.0 + 5.0 * np.sin(2 * np.pi * tc / 5400.0 + 1.0) + rng.normal(0, 0.1, tc.size)
    drift = _lagged(tc, temp, 1500.0)[:, None] * np.array([50.0, -35.0])
    drift += humidity_nm_per_pct * (rh - rh[0])[:, None] * np.array([1.0, -0.7])
    drift += np.cumsum(rng.normal(0, 0.02 * math.sqrt(30.0), (tc.size, 2)), axis=0)
    t, t_end, sign = _frames(n)
    xy = np.column_stack([np.interp(t, tc, drift[:, a]) for a in (0, 1)])
    xy += rng.normal(0, 0.3, xy.shape)
    xy -= xy[0]
    channels = [
        ChannelSample(t_s=float(a), values={"temperature_c": float(b), "humidity_pct": float(c)})
        for a, b, c in zip(tc, temp, rh, strict=True)
    ]
    events = [Event(t_s=0.0, kind=EventKind.POWER_ON)]
    data = RunData.from_arrays(
        t_s=t, xy_nm=xy, scan_sign=sign, t_end_s=t_end, channels=channels, events=events
    )
    return data, xy


@pytest.mark.slow
def test_hidden_humidity_coupling_is_found_and_its_coefficient_recovered() -> None:
    data, _ = _synthetic(humidity_nm_per_pct=3.0, seed=11)
    dg = diagnose(data, PhysicsConfig(terms=["trend", "thermal_lag"]))
    top = dg.candidates[0]
    assert top.effect == "humidity"
    assert top.significant
    assert top.params["k_nm_per_pct_rh_x"] == pytest.approx(3.0, rel=0.15)
    assert top.params["k_nm_per_pct_rh_y"] == pytest.approx(-2.1, rel=0.15)
    assert dg.after_summary is not None
    assert dg.after_summary["rmse_nm"] < 0.7 * dg.summary["rmse_nm"]
    assert dg.config_terms == ["trend", "thermal_lag", "humidity"]
    j = dg.to_json()
    assert j["candidates"][0]["effect"] == "humidity"
    assert 'terms = ["trend", "thermal_lag", "humidity"]' in j["config"]


@pytest.mark.slow
def test_no_false_alarm_when_the_model_is_complete() -> None:
    """Regression guard: a complete model must not get a 'missing effect' finding."""
    data, _ = _synthetic(humidity_nm_per_pct=0.0, seed=12)
    dg = diagnose(data, PhysicsConfig(terms=["trend", "thermal_lag"]))
    assert not any(c.significant for c in dg.candidates)
    assert dg.top is None
    assert dg.finding.startswith("Nothing is missing that these data can show")
    assert dg.to_json()["config"] is None


def test_untestable_candidates_say_why() -> None:
    data, _ = _synthetic(humidity_nm_per_pct=0.0, seed=13, n=30)
    dg = diagnose(
        data,
        PhysicsConfig(terms=["trend"]),
        options=None,
    )
    by_name = {c.effect: c for c in dg.candidates}
    assert not by_name["tip_change"].testable
    assert "tip_change" in by_name["tip_change"].reason


def test_unknown_effect_is_a_config_error() -> None:
    data, _ = _synthetic(humidity_nm_per_pct=0.0, seed=14, n=20)
    with pytest.raises(ConfigError, match="no_such_effect"):
        diagnose(data, PhysicsConfig(), effects=["trend", "no_such_effect"])


def test_too_few_frames_is_an_input_error() -> None:
    with pytest.raises(InputError, match="at least two frames"):
        RunData.from_arrays(t_s=[0.0], xy_nm=[[0.0, 0.0]])


def test_fewer_frames_than_the_candidate_tests_fit_are_refused_not_called_complete() -> None:
    """Regression: ten frames gave "Nothing is missing ... over 0 tests"."""
    data, _ = _synthetic(humidity_nm_per_pct=0.0, seed=16, n=MIN_DIAGNOSE_FRAMES - 1)
    with pytest.raises(TooFewFramesError, match="too few frames: 10 valid, 11 needed") as info:
        diagnose(data, PhysicsConfig(terms=["trend"]))
    assert (info.value.valid, info.value.needed) == (10, 11)
    data, _ = _synthetic(humidity_nm_per_pct=0.0, seed=16, n=MIN_DIAGNOSE_FRAMES)
    tested = diagnose(data, PhysicsConfig(terms=["trend"]))
    assert any(c.testable for c in tested.candidates)


def test_thresholds_are_documented_in_the_json() -> None:
    data, _ = _synthetic(humidity_nm_per_pct=0.0, seed=15, n=30)
    j = diagnose(data, PhysicsConfig(terms=["trend"])).to_json()
    assert j["thresholds"]["min_delta_aicc"] == Thresholds().min_delta_aicc
    for key in ("model_effects", "rmse_nm", "candidates", "failures"):
        assert key in j
    for c in j["candidates"]:
        assert set(c) >= {"effect", "significant", "score", "params", "rmse_after_nm"}


def _replaced(data: RunData, xy: np.ndarray, events: list[Event]) -> RunData:
    """``data`` with other positions and events."""
    return RunData.from_arrays(
        t_s=data.t_s,
        xy_nm=xy,
        scan_sign=data.scan_sign,
        t_end_s=data.t_end_s,
        channels=data.channels,
        events=events,
    )


def test_a_registration_jump_is_called_out_before_the_finding() -> None:
    """Regression guard: a mis-locked frame (a 250 nm step in the measured drift)
    must be flagged, since the candidate tests would otherwise 'explain' it."""
    data, xy = _synthetic(humidity_nm_per_pct=0.0, seed=16, n=40)
    stepped = xy.copy()
    stepped[25:] += [250.0, -80.0]
    dg = diagnose(_replaced(data, stepped, data.events), PhysicsConfig(terms=["trend"]))
    assert dg.finding.startswith("Caution: the measured drift jumps by (+25")
    assert "at t = 7516 s (1 such jump(s))" in dg.finding
    assert any("t = 7516 s (frame 25)" in p for p in dg.patterns)
    clean = diagnose(data, PhysicsConfig(terms=["trend"]))
    assert not clean.finding.startswith("Caution")


def test_a_closed_loop_following_the_drift_is_not_a_string_of_jumps() -> None:
    """Moves the size of the drift between frames (a closed loop) do not make
    every frame a jump (the rule for moves far larger than the drift's steps,
    across which registration can fail, is for those)."""
    data, xy = _synthetic(humidity_nm_per_pct=0.0, seed=16, n=40)
    inc = np.diff(xy, axis=0)
    moves = [
        Event(
            t_s=float(data.t_s[i] + 10.0 * (k + 1)),
            kind=EventKind.OFFSET_MOVE,
            x_nm=float(inc[i, 0] / 5),
            y_nm=float(inc[i, 1] / 5),
        )
        for i in range(inc.shape[0])
        for k in range(5)
    ]
    dg = diagnose(_replaced(data, xy, [*data.events, *moves]), PhysicsConfig(terms=["trend"]))
    assert not any("jumps" in p for p in dg.patterns)
    assert not dg.finding.startswith("Caution")


# --------------------------------------------------------------------------- generic families


def _with_extra(
    data: RunData,
    *,
    name: str,
    values: np.ndarray,
    tc: np.ndarray,
    events: list[Event] | None = None,
    xy: np.ndarray | None = None,
) -> RunData:
    """``data`` with one more logged channel (and events, and positions)."""
    by_t = {c.t_s: dict(c.values) for c in data.channels}
    channels = []
    for t, v in zip(tc, values, strict=True):
        row = by_t.get(float(t), {})
        row[name] = float(v)
        channels.append(ChannelSample(t_s=float(t), values=row))
    return RunData.from_arrays(
        t_s=data.t_s,
        xy_nm=data.xy_nm if xy is None else xy,
        scan_sign=data.scan_sign,
        t_end_s=data.t_end_s,
        channels=channels,
        events=[*data.events, *(events or [])],
    )


def _pressure_case(*, gain: tuple[float, float], seed: int, n: int = 90) -> RunData:
    """The thermal-lag series of :func:`_synthetic` plus a pressure channel that
    moves the sample through a 600 s lag by ``gain`` nm/hPa (built from the equations)."""
    data, xy = _synthetic(humidity_nm_per_pct=0.0, seed=seed, n=n)
    tc = np.array([c.t_s for c in data.channels])
    rng = np.random.default_rng(seed + 100)
    p = 1013.0 + np.cumsum(rng.normal(0.0, 0.07, tc.size)) + rng.normal(0, 0.02, tc.size)
    lagged = _lagged(tc, p, 600.0)
    shift = np.column_stack([np.interp(data.t_s, tc, lagged) * g for g in gain])
    return _with_extra(data, name="pressure_hpa", values=p, tc=tc, xy=xy + shift - shift[0])


def test_family_candidates_cover_every_channel_and_event_kind() -> None:
    from afmdrift.diagnostics._candidates import family_candidates

    data = _pressure_case(gain=(0.0, 0.0), seed=21, n=20)
    h = data.history()
    h.add_events([Event(100.0, "door_open"), Event(900.0, "door_open")])
    h.add_events([Event(50.0 * k, "tip_approach") for k in range(1, 13)])
    specs = family_candidates(h, ["trend", "channel:pressure_hpa"])
    assert "channel:pressure_hpa#2" in specs  # a second path next to the model's
    assert {"channel:temperature_c", "channel:humidity_pct"} <= set(specs)
    assert {"event:power_on", "event:power_on:log"} <= set(specs)
    assert "event:power_on:each" not in specs  # logged once: shared = per event
    assert {"event:door_open:each", "event:door_open:log:each"} <= set(specs)
    assert "event:tip_approach" in specs
    assert "event:tip_approach:each" not in specs  # 12 free amplitudes: not tested


def test_named_effect_ranks_above_a_generic_term_with_comparable_evidence() -> None:
    """Regression guard: channel:humidity_pct (a lag smooths the noisy sensor) must
    not displace humidity when it fits a few AICc units better but predicts no better."""
    from afmdrift.diagnostics._candidates import CandidateResult
    from afmdrift.diagnostics._ranking import rank_candidates as _rank

    def cand(
        name: str, d_aicc: float, rmse: float, driver: dict[str, str], tau_s: float = 1.0
    ) -> CandidateResult:
        return CandidateResult(
            effect=name,
            testable=True,
            significant=True,
            score=d_aicc,
            delta_aicc=d_aicc,
            rmse_after_nm=rmse,
            rmse_after_kind="replayed",
            driver=driver,
            channel=driver.get("channel", "humidity_pct" if name == "humidity" else None),
            nonlinear={"tau_s": tau_s} if driver else {},
        )

    generic = cand("channel:humidity_pct", 836.0, 1.80, {"channel": "humidity_pct"})
    named = cand("humidity", 823.0, 1.85, {})
    results = [generic, named]
    _rank(results, Thresholds())
    assert results[0].effect == "humidity"
    # Far better evidence and prediction: the generic term stays first.
    far = cand("channel:pressure_hpa", 400.0, 1.0, {"channel": "pressure_hpa"})
    weak = cand("thermal", 40.0, 1.9, {})
    results = [weak, far]
    _rank(results, Thresholds())
    assert results[0].effect == "channel:pressure_hpa"
    # A lag shorter than the frame period on the named term's own channel cannot be
    # resolved by frames: the named direct response ranks first even when the
    # generic term fits better; a lag of several frames is another effect.
    short = cand("channel:humidity_pct", 802.0, 1.39, {"channel": "humidity_pct"}, 13.5)
    results = [short, cand("humidity", 772.0, 1.82, {})]
    _rank(results, Thresholds(), frame_period_s=300.0)
    assert results[0].effect == "humidity"
    long = cand("channel:humidity_pct", 802.0, 1.39, {"channel": "humidity_pct"}, 1800.0)
    results = [long, cand("humidity", 772.0, 1.82, {})]
    _rank(results, Thresholds(), frame_period_s=300.0)
    assert results[0].effect == "channel:humidity_pct"


@pytest.mark.slow
def test_out_of_library_channel_is_named_with_driver_lag_and_gain() -> None:
    data = _pressure_case(gain=(8.0, -6.0), seed=22)
    dg = diagnose(data, PhysicsConfig(terms=["trend", "thermal_lag"]))
    top = dg.candidates[0]
    assert top.significant
    assert top.driver == {"channel": "pressure_hpa"}
    j = dg.to_json()["candidates"][0]
    assert j["term"] == "channel:pressure_hpa"
    assert j["family"] == "channel"
    assert j["params"]["channel"] == "pressure_hpa"
    assert j["params"]["tau_s"] == pytest.approx(600.0, rel=0.35)
    assert j["params"]["gain_nm_per_hpa_x"] == pytest.approx(8.0, rel=0.15)
    assert j["params"]["gain_nm_per_hpa_y"] == pytest.approx(-6.0, rel=0.15)
    assert "No library effect explains it" in dg.finding
    assert "pressure_hpa" in dg.finding
    assert dg.config_terms == ["trend", "thermal_lag", "channel:pressure_hpa"]
    assert dg.after_summary is not None
    assert dg.after_summary["rmse_nm"] < 0.7 * dg.summary["rmse_nm"]
    # The report overlays the driver on the errors.
    from afmdrift.diagnostics._report import render_report

    page = render_report(dg, data)
    assert 'alt="driver of the leading generic candidate over the errors"' in page
    assert "channel:pressure_hpa" in page
    # The term is accepted verbatim as a model term (--effects, [model.physics] terms).
    assert [t.name for t in PhysicsPredictor(PhysicsConfig(terms=dg.config_terms)).terms] == [
        "trend",
        "thermal_lag",
        "channel:pressure_hpa",
    ]


@pytest.mark.slow
def test_distractor_channel_and_events_raise_no_finding() -> None:
    """Regression guard: a logged channel and event kind that do not move the sample
    must not become a finding now that every channel and kind is a candidate."""
    data = _pressure_case(gain=(0.0, 0.0), seed=23)
    extra = [Event(6000.0, "door_open"), Event(14000.0, "door_open"), Event(21000.0, "door_open")]
    data = RunData.from_arrays(
        t_s=data.t_s,
        xy_nm=data.xy_nm,
        scan_sign=data.scan_sign,
        t_end_s=data.t_end_s,
        channels=data.channels,
        events=[*data.events, *extra],
    )
    dg = diagnose(data, PhysicsConfig(terms=["trend", "thermal_lag"]))
    testable = {c.effect for c in dg.candidates if c.testable}
    assert {"channel:pressure_hpa", "event:door_open", "event:door_open:each"} <= testable
    assert dg.top is None, dg.finding
    assert dg.n_tests > 100


def test_forecast_comparison_holds_its_level_on_equally_good_autocorrelated_errors() -> None:
    """Two models with equally good, autocorrelated (AR(1), φ 0.7) and
    correlated errors: the one-sided Diebold-Mariano p-value falls below 0.05
    in about 5 % of records, not more (the HAC variance pays for the
    autocorrelation; a plain t-test would not)."""
    rng = np.random.default_rng(11)
    rejections = 0
    trials = 400
    for _ in range(trials):
        shocks = rng.normal(size=(3, 100, 2))
        e = np.zeros_like(shocks)
        for k in range(1, 100):
            e[:, k] = 0.7 * e[:, k - 1] + shocks[:, k]
        common = e[0]
        p, m = forecast_comparison(common + e[1], common + e[2])
        assert m == 100
        rejections += p < 0.05
    assert rejections / trials < 0.09, rejections


def test_forecast_comparison_finds_a_real_improvement() -> None:
    rng = np.random.default_rng(3)
    base = rng.normal(0.0, 1.0, size=(100, 2))
    better = 0.7 * base + rng.normal(0.0, 0.2, size=(100, 2))
    p, _ = forecast_comparison(base, better)
    assert p < 1e-3
    p_back, _ = forecast_comparison(better, base)
    assert p_back > 0.99


def test_holm_adjustment_is_step_down_and_monotone() -> None:
    from afmdrift.diagnostics._candidates import CandidateResult
    from afmdrift.diagnostics._ranking import _holm

    cs = [CandidateResult(effect=n, testable=True) for n in "abcd"]
    for c, p in zip(cs, [0.004, 0.0012, 0.03, math.nan], strict=True):
        c.p_online = p
    _holm(cs)
    assert cs[1].p_online_holm == pytest.approx(4 * 0.0012)
    assert cs[0].p_online_holm == pytest.approx(3 * 0.004)
    assert cs[2].p_online_holm == pytest.approx(2 * 0.03)
    assert math.isnan(cs[3].p_online_holm)


@pytest.mark.slow
def test_a_missing_effect_must_cut_the_online_error_by_the_minimum_effect() -> None:
    """The hidden humidity coupling is found; asked for an effect size no
    candidate reaches, diagnose reports nothing missing and names the closest."""
    data, _ = _synthetic(humidity_nm_per_pct=3.0, seed=11)
    dg = diagnose(data, PhysicsConfig(), effects=["trend", "thermal_lag"])
    assert dg.top is not None
    assert dg.top.effect == "humidity"
    drop = dg.top.prequential_drop
    assert drop is not None
    assert drop >= 0.10
    strict = DiagnoseOptions(thresholds=Thresholds(min_effect=min(drop + 0.05, 0.99)))
    dg2 = diagnose(data, PhysicsConfig(), effects=["trend", "thermal_lag"], options=strict)
    assert dg2.top is None
    assert "The closest candidate is humidity" in dg2.finding


def test_wald_test_of_a_rank_deficient_candidate_counts_its_rank() -> None:
    """Two identical candidate columns are one degree of freedom, and no
    statsmodels warning (warnings are errors here) escapes."""
    from afmdrift.diagnostics._regression import _wald

    rng = np.random.default_rng(0)
    col = rng.normal(size=80)
    e0 = 0.5 * col + rng.normal(size=80)
    w, k, _ = _wald(np.column_stack([col, col]), e0, lags=3)
    assert k == 1
    w1, k1, _ = _wald(col[:, None], e0, lags=3)
    assert k1 == 1
    assert w == pytest.approx(w1, rel=1e-6)


def test_own_statistics_equal_scipy_and_statsmodels() -> None:
    """Ljung–Box, Lomb's power, Welch's t-test and the OLS/HAC covariances are
    computed here with numpy (their libraries' imports cost a second of every
    diagnosis); they must give the libraries' numbers."""
    from scipy import signal, stats
    from statsmodels.regression.linear_model import OLS
    from statsmodels.stats.diagnostic import acorr_ljungbox

    from afmdrift.diagnostics._regression import ols_hac
    from afmdrift.diagnostics._stats import _lomb_power, welch_p

    rng = np.random.default_rng(7)
    e = np.cumsum(rng.normal(size=150)) * 0.2 + rng.normal(size=150)
    for lags in (1, 5, 10):
        q, p, used = ljung_box(e, lags=lags)
        ref = acorr_ljungbox(e, lags=[lags], return_df=True)
        assert used == lags
        assert q == pytest.approx(float(ref["lb_stat"].iloc[0]), rel=1e-10)
        assert p == pytest.approx(float(ref["lb_pvalue"].iloc[0]), rel=1e-8, abs=1e-300)
    t = np.sort(rng.uniform(0.0, 5e3, 200))
    y = np.sin(t / 200.0) + rng.normal(size=200)
    y -= y.mean()
    w = 2 * np.pi / np.geomspace(50.0, 5e3, 60)
    np.testing.assert_allclose(
        _lomb_power(t, y, w), signal.lombscargle(t, y, w, normalize=True), atol=1e-12
    )
    a, b = rng.normal(size=20), rng.normal(0.7, 3.0, size=33)
    assert welch_p(a, b) == pytest.approx(
        float(stats.ttest_ind(a, b, equal_var=False).pvalue), rel=1e-10
    )
    z = rng.normal(size=(90, 3))
    yy = z @ np.array([1.0, 0.0, -0.3]) + np.cumsum(rng.normal(size=90)) * 0.3
    fit = OLS(yy, z).fit()
    hac = fit.get_robustcov_results(cov_type="HAC", maxlags=3, use_correction=True)
    gamma, v_ols, v_hac = ols_hac(z, yy, 3)
    np.testing.assert_allclose(gamma, fit.params, rtol=1e-10)
    np.testing.assert_allclose(v_ols, fit.cov_params(), rtol=1e-10)
    np.testing.assert_allclose(v_hac, hac.cov_params(), rtol=1e-10)


def test_repeated_diagnoses_spend_alpha_so_the_whole_run_stays_at_alpha() -> None:
    """Guards against a run's sequence of live diagnoses each testing at the full
    alpha: the K-th look is tested at alpha*6/(pi^2 K^2), summing to at most alpha."""
    base = Thresholds(alpha=0.01)
    looks = [base.at_look(k) for k in range(1, 100_001)]
    assert sum(t.alpha for t in looks) <= base.alpha
    assert sum(t.alpha for t in looks) > 0.9999 * base.alpha
    assert looks[0].alpha == pytest.approx(0.01 * 6 / math.pi**2)
    assert all(t.run_alpha == 0.01 and t.look == k for k, t in enumerate(looks, 1))
    # A look of a look spends from the run's level, not from the look's.
    assert looks[4].at_look(2).alpha == base.at_look(2).alpha
    with pytest.raises(ValueError, match=r"look must be >= 1.*got 0"):
        base.at_look(0)
