"""Effect terms and the physics model: each term recovers its physical parameters,
plugins load from a module path and from an entry point."""

from __future__ import annotations

import pickle
import sys
import textwrap
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest

from afmdrift.errors import ConfigError
from afmdrift.model import (
    LIBRARY,
    EffectTerm,
    History,
    NonlinearParam,
    Observation,
    PhysicsConfig,
    PhysicsPredictor,
    available_terms,
    load_term_class,
    make_term,
    parse_term_spec,
    scan_samples,
)
from afmdrift.model._effects import (
    log_creep_sum,
    offset_through_play,
    play_gaps,
    step_through_play,
)
from afmdrift.model._synthetic import synthetic_series
from afmdrift.records import ChannelSample, Event, EventKind, ScanDirection

PERIOD_S = 256.0


def _feed(
    model: PhysicsPredictor,
    t: np.ndarray,
    xy: np.ndarray,
    history: History,
    directions: list[ScanDirection] | None = None,
    sigma_nm: float = 0.2,
) -> None:
    for i, ti in enumerate(t):
        d = directions[i] if directions else ScanDirection.UP
        model.update(
            Observation(float(ti), float(xy[i, 0]), float(xy[i, 1]), sigma_nm, d, i), history
        )


def _temperature_history(t_end_s: float, *, period_s: float = 10.0) -> History:
    h = History()
    tc = np.arange(0.0, t_end_s + 600.0, period_s)
    temp = 22.0 + 0.5 * np.sin(2 * np.pi * tc / 7200.0) + 0.2 * np.sin(2 * np.pi * tc / 2500.0)
    hum = 45.0 + 3.0 * np.sin(2 * np.pi * tc / 9000.0 + 1.0)
    for a, b, c in zip(tc, temp, hum, strict=True):
        h.add_channels(
            ChannelSample(float(a), {"temperature_c": float(b), "humidity_pct": float(c)})
        )
    return h


def test_library_has_the_canonical_terms() -> None:
    assert set(LIBRARY) == {
        "trend",
        "thermal",
        "thermal_lag",
        "humidity",
        "creep",
        "warmup",
        "warmup_two",
        "scan_direction",
        "hysteresis",
        "tip_change",
    }
    for cls in LIBRARY.values():
        assert cls.__doc__, cls.name
        assert "p(t)" in cls.__doc__, cls.name


def test_thermal_lag_time_constant_recovered_within_20_percent() -> None:
    s = synthetic_series(
        hours=8.0, thermal_tau_s=1500.0, noise_nm=0.3, moves=(), scan_bias_nm=(0.0, 0.0), seed=3
    )
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "thermal_lag"], residual="none"))
    for o in s.observations:
        model.update(o, s.history)
    tau = model.params["thermal_lag"]["tau_s"]
    assert abs(tau - 1500.0) / 1500.0 < 0.2, tau
    k = model.coefficients()["thermal_lag"]
    assert k["x"][0] == pytest.approx(25.0, rel=0.1)
    assert k["y"][0] == pytest.approx(12.0, rel=0.1)


def test_creep_fraction_and_onset_recovered() -> None:
    s = synthetic_series(
        hours=6.0,
        temperature_amplitude_k=0.0,
        creep_fraction=0.1,
        creep_t0_s=30.0,
        moves=((3000.0, 400.0, -300.0),),
        scan_bias_nm=(0.0, 0.0),
        noise_nm=0.1,
        seed=4,
    )
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "creep"], residual="none"))
    for o in s.observations:
        model.update(o, s.history)
    c = model.coefficients()["creep"]
    assert c["x"][0] == pytest.approx(0.1, rel=0.1)
    assert c["y"][0] == pytest.approx(0.1, rel=0.1)
    t0 = model.params["creep"]["t0_s"]
    assert 30.0 / 1.5 < t0 < 30.0 * 1.5, t0


def test_warmup_amplitude_and_time_constant_recovered() -> None:
    t = np.arange(128.0, 8 * 3600.0, PERIOD_S)
    tau_w, amp = 5000.0, np.array([300.0, -200.0])
    xy = (1 - np.exp(-t / tau_w))[:, None] * amp[None, :]
    xy -= xy[0]
    h = History()
    h.add_events([Event(0.0, EventKind.POWER_ON)])
    model = PhysicsPredictor(PhysicsConfig(terms=["warmup"], residual="none"))
    _feed(model, t, xy, h)
    assert model.params["warmup"]["tau_w_s"] == pytest.approx(tau_w, rel=0.05)
    assert model.coefficients()["warmup"]["x"][0] == pytest.approx(300.0, rel=0.05)


def test_linear_terms_recovered_together() -> None:
    """thermal (nm/K), humidity (nm/%RH), scan-direction bias, hysteresis, tip change, trend."""
    t = np.arange(128.0, 10 * 3600.0, PERIOD_S)
    h = _temperature_history(float(t[-1]))
    h.add_events(
        [
            Event(9000.0, EventKind.OFFSET_MOVE, 100.0, -50.0),
            Event(20000.0, EventKind.OFFSET_MOVE, -80.0, 60.0),
            Event(15000.0, EventKind.TIP_CHANGE),
        ]
    )
    sign = np.where(np.arange(t.size) % 2 == 0, 1.0, -1.0)
    temp = h.channel_at("temperature_c", t) - 22.0
    hum = h.channel_at("humidity_pct", t) - h.channel_at("humidity_pct", [0.0])[0]
    last_sign = np.where(t > 20000, -1.0, np.where(t > 9000, 1.0, 0.0))
    truth = {
        "thermal": (30.0, -10.0),
        "humidity": (2.0, 1.0),
        "scan_direction": (3.0, -2.0),
        "hysteresis": (4.0, 2.5),
        "tip_change": (7.0, -5.0),
        "velocity": (5.0, -3.0),
    }
    xy = np.zeros((t.size, 2))
    for a in (0, 1):
        ls = last_sign if a == 0 else -last_sign
        xy[:, a] = (
            truth["thermal"][a] * temp
            + truth["humidity"][a] * hum
            + truth["scan_direction"][a] * sign / 2
            + truth["hysteresis"][a] * ls
            + truth["tip_change"][a] * (t > 15000)
            + truth["velocity"][a] * t / 3600
            + 11.0
        )
    dirs = [ScanDirection.UP if s > 0 else ScanDirection.DOWN for s in sign]
    terms = ["trend", "thermal", "humidity", "scan_direction", "hysteresis", "tip_change"]
    model = PhysicsPredictor(PhysicsConfig(terms=terms, residual="none"))
    _feed(model, t, xy, h, dirs)
    c = model.coefficients()
    for a, axis in enumerate("xy"):
        assert c["thermal"][axis][0] == pytest.approx(truth["thermal"][a], abs=0.05)
        assert c["humidity"][axis][0] == pytest.approx(truth["humidity"][a], abs=0.05)
        assert c["scan_direction"][axis][0] == pytest.approx(truth["scan_direction"][a], abs=0.05)
        assert c["hysteresis"][axis][0] == pytest.approx(truth["hysteresis"][a], abs=0.05)
        assert c["tip_change"][axis][0] == pytest.approx(truth["tip_change"][a], abs=0.05)
        assert c["trend"][axis][1] == pytest.approx(truth["velocity"][a], abs=0.05)


def test_missing_channel_leaves_term_out_and_model_still_predicts() -> None:
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "thermal_lag", "humidity"]))
    h = History()
    t = np.arange(128.0, 4000.0, PERIOD_S)
    _feed(model, t, np.column_stack([t * 0.01, -t * 0.02]), h)
    assert model.active == ["trend"]
    p = model.predict([t[-1] + PERIOD_S], h).mean_nm[0]
    assert p == pytest.approx([(t[-1] + PERIOD_S) * 0.01, -(t[-1] + PERIOD_S) * 0.02], abs=1e-6)


def test_future_scan_direction_alternates() -> None:
    """Regression: an alternating up/down series must predict the next frame's bias sign."""
    t = np.arange(128.0, 30 * PERIOD_S, PERIOD_S)
    sign = np.where(np.arange(t.size) % 2 == 0, 1.0, -1.0)
    xy = np.column_stack([2.0 * sign, np.zeros_like(t)])
    dirs = [ScanDirection.UP if s > 0 else ScanDirection.DOWN for s in sign]
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "scan_direction"], residual="none"))
    _feed(model, t, xy, History(), dirs)
    nxt = model.predict([t[-1] + PERIOD_S, t[-1] + 2 * PERIOD_S], History()).mean_nm
    assert nxt[0, 0] == pytest.approx(-2.0 * sign[-1], abs=1e-6)
    assert nxt[1, 0] == pytest.approx(2.0 * sign[-1], abs=1e-6)
    # The tip follows the sample, not the measurement artefact.
    drift = model.predict_drift([t[-1] + PERIOD_S], History()).mean_nm
    assert drift[0, 0] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("reference", [ScanDirection.UP, ScanDirection.DOWN])
def test_drift_is_what_a_frame_scanned_like_the_reference_shows(reference: ScanDirection) -> None:
    """Positions are measured against the session reference, so the scan-direction
    bias cancels in frames of its direction and shifts the others by the whole
    up-minus-down bias. The drift the tip follows is the former, not the midpoint
    (which put a closed loop half a bias off, 1 nm in y on the default scenario)."""
    t = np.arange(128.0, 30 * PERIOD_S, PERIOD_S)
    sign = np.where(np.arange(t.size) % 2 == 0, 1.0, -1.0)
    ref = 1.0 if reference is ScanDirection.UP else -1.0
    bias = np.array([0.5, 2.0])
    p = np.column_stack([0.01 * t, -0.005 * t])
    xy = p + 0.5 * (sign - ref)[:, None] * bias[None, :]
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "scan_direction"], residual="none"))
    for i, ti in enumerate(t):
        d = ScanDirection.UP if sign[i] > 0 else ScanDirection.DOWN
        obs = Observation(float(ti), float(xy[i, 0]), float(xy[i, 1]), 0.2, d, i, reference)
        model.update(obs, History())
    t_next = t[-1] + PERIOD_S
    drift = model.predict_drift([t_next], History()).mean_nm[0]
    assert drift == pytest.approx([0.01 * t_next, -0.005 * t_next], abs=1e-6)
    # The state round trip keeps the reference's direction.
    again = PhysicsPredictor(PhysicsConfig(terms=["trend", "scan_direction"], residual="none"))
    again.load_state_dict(model.state_dict())
    assert again.predict_drift([t_next], History()).mean_nm[0] == pytest.approx(drift, abs=1e-9)


def test_unknown_term_is_a_config_error_naming_it() -> None:
    with pytest.raises(ConfigError, match="'thermall'"):
        PhysicsPredictor(PhysicsConfig(terms=["trend", "thermall"]))


class Sinusoid(EffectTerm):
    """A periodic disturbance: p(t) = a·sin(2πt/P) + b·cos(2πt/P), period ``period_s``."""

    name = "test_sinusoid"
    nonlinear_params = (NonlinearParam("period_s", 600.0, 20000.0, 3000.0, grid_points=25),)

    def design(
        self,
        t_s: np.ndarray,
        history: History,
        *,
        scan_sign: np.ndarray,
        params: Mapping[str, float],
        axis: int,
    ) -> np.ndarray:
        w = 2 * np.pi * t_s / params["period_s"]
        return np.column_stack([np.sin(w), np.cos(w)])


def test_plugin_term_from_module_path_is_fitted() -> None:
    spec = f"{__name__}:Sinusoid"
    assert load_term_class(spec) is Sinusoid
    t = np.arange(128.0, 12 * 3600.0, PERIOD_S)
    xy = np.column_stack([20 * np.sin(2 * np.pi * t / 5400.0), 5 * np.cos(2 * np.pi * t / 5400.0)])
    model = PhysicsPredictor(
        PhysicsConfig(terms=["trend", "test_sinusoid"], plugins=[spec], residual="none")
    )
    _feed(model, t, xy, History())
    assert model.params["test_sinusoid"]["period_s"] == pytest.approx(5400.0, rel=0.01)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("no_colon_here", "expected 'package.module:ClassName'"),
        ("afmdrift_no_such_module:X", "cannot import"),
        (f"{__name__}:NotThere", "has no 'NotThere'"),
        (f"{__name__}:PERIOD_S", "not an EffectTerm subclass"),
    ],
)
def test_bad_plugin_spec_is_a_config_error(spec: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_term_class(spec)


def test_plugin_may_not_shadow_a_library_term(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "shadowing_term.py").write_text(
        textwrap.dedent('''
        from afmdrift.model import EffectTerm
        class Fake(EffectTerm):
            """p(t) = 0."""
            name = "thermal"
            def design(self, t_s, history, *, scan_sign, params, axis):
                return t_s[:, None] * 0
    ''')
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ConfigError, match="taken by the built-in library"):
        available_terms(["shadowing_term:Fake"])


def test_entry_point_plugin_is_discovered(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A term registered under the ``afmdrift.effects`` entry-point group by an installed
    distribution is available by name without any configuration."""
    pkg = tmp_path / "afmdrift_test_effects"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(
        textwrap.dedent('''
        import numpy as np
        from afmdrift.model import EffectTerm
        class Quadratic(EffectTerm):
            """p(t) = q·(t/3600)², q in nm/h²."""
            name = "test_quadratic"
            def design(self, t_s, history, *, scan_sign, params, axis):
                return (t_s / 3600.0)[:, None] ** 2
    ''')
    )
    dist = tmp_path / "afmdrift_test_effects-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: afmdrift-test-effects\nVersion: 1.0\n"
    )
    (dist / "entry_points.txt").write_text(
        "[afmdrift.effects]\ntest_quadratic = afmdrift_test_effects:Quadratic\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "test_quadratic" in available_terms()
    t = np.arange(128.0, 6 * 3600.0, PERIOD_S)
    xy = np.column_stack([3.0 * (t / 3600) ** 2, -((t / 3600) ** 2)])
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "test_quadratic"], residual="none"))
    _feed(model, t, xy, History())
    assert model.coefficients()["test_quadratic"]["x"][0] == pytest.approx(3.0, abs=1e-6)
    sys.modules.pop("afmdrift_test_effects", None)


def test_nonlinear_grid_spans_bounds() -> None:
    term = LIBRARY["thermal_lag"]()
    grid = [g["tau_s"] for g in term.nonlinear_grid()]
    p = term.nonlinear_params[0]
    assert grid[0] == pytest.approx(p.lower)
    assert grid[-1] == pytest.approx(p.upper)
    assert LIBRARY["trend"]().nonlinear_grid() == [{}]


def test_scan_direction_left_out_when_every_frame_scans_up() -> None:
    """Regression: with only up frames the scan_direction column duplicated the intercept;
    the minimum-norm split put an arbitrary offset into the term that d(t) leaves out."""
    t = np.arange(128.0, 20 * PERIOD_S, PERIOD_S)
    xy = np.column_stack([50.0 + 0.01 * t, -20.0 + 0.0 * t])
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "scan_direction"], residual="none"))
    _feed(model, t, xy, History())
    assert model.active == ["trend"]
    drift = model.predict_drift([t[-1] + PERIOD_S], History()).mean_nm[0]
    assert drift == pytest.approx([50.0 + 0.01 * (t[-1] + PERIOD_S), -20.0], abs=1e-6)


def test_fit_uses_only_the_most_recent_max_points() -> None:
    """Bounded cost per frame: with max_points=10 an old jump no longer biases the trend."""
    t = np.arange(128.0, 40 * PERIOD_S, PERIOD_S)
    xy = np.column_stack([0.02 * t + np.where(t < 3000, 100.0, 0.0), np.zeros_like(t)])
    cfg = PhysicsConfig(terms=["trend"], residual="none", memory_s=0, max_points=10)
    model = PhysicsPredictor(cfg)
    _feed(model, t, xy, History())
    assert model.coefficients()["trend"]["x"][1] == pytest.approx(0.02 * 3600, abs=1e-6)


# --------------------------------------------------------------------------- generic terms


def _lag_series(t: np.ndarray, c: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag of ``c`` sampled at ``t``, minus its start (built independently)."""
    out = np.empty_like(c)
    out[0] = c[0]
    for k in range(1, t.size):
        a = np.exp(-(t[k] - t[k - 1]) / tau_s)
        out[k] = a * out[k - 1] + (1 - a) * c[k]
    return out - c[0]


def _channel_history(tc: np.ndarray, name: str, values: np.ndarray) -> History:
    h = History()
    for a, b in zip(tc, values, strict=True):
        h.add_channels(ChannelSample(float(a), {name: float(b)}))
    return h


def _pressure(tc: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(0.0, 0.05, tc.size))
    return 1013.0 + 1.5 * np.sin(2 * np.pi * tc / 9000.0) + walk


def test_channel_term_spec_recovers_lag_and_gain_of_any_channel() -> None:
    tc = np.arange(0.0, 8 * 3600.0 + 600.0, 10.0)
    p = _pressure(tc, 1)
    drift = _lag_series(tc, p, 600.0)[:, None] * np.array([8.0, -6.0])
    t = np.arange(128.0, 8 * 3600.0, PERIOD_S)
    xy = np.column_stack([np.interp(t, tc, drift[:, a]) for a in (0, 1)])
    model = PhysicsPredictor(
        PhysicsConfig(terms=["trend", "channel:pressure_hpa"], residual="none")
    )
    _feed(model, t, xy, _channel_history(tc, "pressure_hpa", p))
    assert model.params["channel:pressure_hpa"]["tau_s"] == pytest.approx(600.0, rel=0.2)
    g = model.coefficients()["channel:pressure_hpa"]
    assert g["x"][0] == pytest.approx(8.0, rel=0.05)
    assert g["y"][0] == pytest.approx(-6.0, rel=0.05)


def test_channel_term_without_lag_is_the_direct_response() -> None:
    """τ at the bottom of the grid (1 s) is computed as no lag: p = g·(C − C₀) exactly,
    C the channel read through its noise (a clean channel, as here, unchanged)."""
    tc = np.arange(0.0, 4000.0, 10.0)
    c = np.sin(tc / 300.0)
    term = parse_term_spec("channel:laser_power_mw")()
    t = np.array([5.0, 1234.0, 3000.0])
    history = _channel_history(tc, "laser_power_mw", c)
    col = term.design(t, history, scan_sign=np.ones(3), params={"tau_s": 1.0}, axis=0)
    np.testing.assert_array_equal(col[:, 0], history.sensed_at("laser_power_mw", t) - c[0])
    np.testing.assert_allclose(col[:, 0], np.interp(t, tc, c) - c[0], atol=1e-5)
    assert term.coefficient_units == ("gain_nm_per_mw",)


def test_two_instances_of_one_channel_fit_a_fast_and_a_slow_path() -> None:
    tc = np.arange(0.0, 10 * 3600.0 + 600.0, 10.0)
    rng = np.random.default_rng(2)
    stage = 25.0 + 0.4 * np.sin(2 * np.pi * tc / 2400.0) + np.cumsum(rng.normal(0, 0.004, tc.size))
    drift = _lag_series(tc, stage, 120.0)[:, None] * np.array([25.0, 15.0])
    drift += _lag_series(tc, stage, 2400.0)[:, None] * np.array([60.0, -45.0])
    t = np.arange(128.0, 10 * 3600.0, PERIOD_S)
    xy = np.column_stack([np.interp(t, tc, drift[:, a]) for a in (0, 1)])
    fast, slow = "channel:stage_c:tau_s=1..600#fast", "channel:stage_c:tau_s=600..20000#slow"
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", fast, slow], residual="none"))
    _feed(model, t, xy, _channel_history(tc, "stage_c", stage))
    assert model.params[fast]["tau_s"] == pytest.approx(120.0, rel=0.3)
    assert model.params[slow]["tau_s"] == pytest.approx(2400.0, rel=0.3)
    assert model.coefficients()[slow]["y"][0] == pytest.approx(-45.0, rel=0.15)


def test_event_term_fits_settling_after_a_kind_the_library_does_not_know() -> None:
    t = np.arange(128.0, 8 * 3600.0, PERIOD_S)
    times = [4000.0, 11000.0, 19000.0]
    h = History()
    h.add_events([Event(0.0, EventKind.POWER_ON)] + [Event(x, "stage_move") for x in times])
    resp = sum(np.where(t > x, -np.expm1(-(t - x) / 900.0), 0.0) for x in times)
    xy = np.asarray(resp)[:, None] * np.array([25.0, -18.0])
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "event:stage_move"], residual="none"))
    _feed(model, t, xy, h)
    assert model.params["event:stage_move"]["tau_s"] == pytest.approx(900.0, rel=0.1)
    assert model.coefficients()["event:stage_move"]["x"][0] == pytest.approx(25.0, rel=0.05)
    each = parse_term_spec("event:stage_move:each:tau_s=900")()
    cols = each.design(t, h, scan_sign=np.ones(t.size), params={}, axis=0)
    assert cols.shape == (t.size, 3)
    np.testing.assert_allclose(cols.sum(axis=1), resp)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("channel:", "expected 'channel:<channel>"),
        ("event:door_open:slow", "unknown option 'slow'"),
        ("channel:p_hpa:tau_s=0..10", "'tau_s=0..10' must be positive"),
        ("channel:p_hpa:tau_s=ten", "needs a number or a range"),
        ("event:door_open:log:tau_s=5", "the log shape has t0_s, not tau_s"),
        ("event:Door", "event kind 'Door'"),
        ("channel:p_hpa#Fast", "label 'Fast'"),
        ("channel:p_hpa:t0_s=3", "unknown parameter 't0_s'"),
    ],
)
def test_malformed_term_spec_names_the_spec_and_the_part(spec: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        PhysicsPredictor(PhysicsConfig(terms=["trend", spec]))
    assert str(err.value).startswith("model.physics.terms:")
    assert repr(spec) in str(err.value)


def test_duplicate_term_specs_are_rejected_and_labels_make_them_distinct() -> None:
    with pytest.raises(ConfigError, match="duplicate"):
        PhysicsPredictor(PhysicsConfig(terms=["channel:stage_c", "channel:stage_c"]))
    model = PhysicsPredictor(PhysicsConfig(terms=["channel:stage_c", "channel:stage_c#2"]))
    assert [t.name for t in model.terms] == ["channel:stage_c", "channel:stage_c#2"]
    assert make_term("event:door_open:log").name == "event:door_open:log"


@pytest.mark.parametrize("t0_s", [0.3, 10.0, 3000.0])
def test_creep_of_thousands_of_moves_is_the_exact_sum(t0_s: float) -> None:
    """A closed loop logs a move every few seconds: far moves go by bins (the
    exact sum of 720 moves at 2000 times is the reference)."""
    rng = np.random.default_rng(3)
    t_moves = np.sort(rng.uniform(0.0, 7200.0, 720))
    steps = rng.normal(size=720) * (rng.random(720) > 0.3)
    t = np.sort(rng.uniform(-100.0, 8000.0, 2000))
    exact = np.log10(1.0 + np.maximum(t[:, None] - t_moves[None, :], 0.0) / t0_s) @ steps
    got = log_creep_sum(t, t_moves, steps, t0_s)
    # the documented bound (3e-4 of the binned steps), and 1e-4 of the creep itself
    assert np.max(np.abs(got - exact)) < 3e-4 * np.abs(steps).sum()
    assert np.max(np.abs(got - exact)) < 1e-4 * np.max(np.abs(exact))
    assert np.all(got[t <= t_moves[0]] == 0.0)


def test_event_arrays_follow_the_log() -> None:
    history = History()
    history.add_events([Event(10.0, EventKind.OFFSET_MOVE, 1.0, 2.0)])
    t, xy = history.of_kind(EventKind.OFFSET_MOVE)
    assert t.tolist() == [10.0]
    assert xy.tolist() == [[1.0, 2.0]]
    history.add_events([Event(5.0, EventKind.OFFSET_MOVE, -1.0, 0.0), Event(7.0, "door")])
    t, xy = history.of_kind(EventKind.OFFSET_MOVE)
    assert t.tolist() == [5.0, 10.0]
    assert xy[:, 0].tolist() == [-1.0, 1.0]
    assert history.of_kind("door")[0].tolist() == [7.0]
    assert history.of_kind(EventKind.POWER_ON)[0].size == 0


def test_play_gaps_and_their_inverse() -> None:
    """The gap g = y − c of a play of half-width r, and the step that moves the
    content by a wanted amount through it (checked by applying it)."""
    np.testing.assert_allclose(play_gaps([1.0, 1.0, -0.5, -3.0], 1.0), [-1.0, -1.0, -0.5, 1.0])
    np.testing.assert_allclose(play_gaps([0.2], 1.0, gap0_nm=0.9), [0.7])
    for want in (-5.0, -1.0, -0.2, 0.0, 0.3, 1.0, 5.0):
        for gap in (-1.0, 0.0, 0.5):
            for gain in (1.0, -0.5, 0.0, 1.5, -1.0):
                step = step_through_play(want, gap, 1.0, gain)
                after = float(np.clip(gap - step, -1.0, 1.0))
                assert step - gain * (after - gap) == pytest.approx(want, abs=1e-9)
    with pytest.raises(ValueError, match="gain"):
        step_through_play(1.0, 0.0, 1.0, -1.5)


def test_hysteresis_play_and_gain_recovered_from_small_moves_back_and_forth() -> None:
    """A closed loop moves the offset in small steps that reverse: the position
    follows the scanner's play gap (r = 2 nm, gain 1 in x, 0.5 in y), which the
    sign of the last move cannot describe."""
    rng = np.random.default_rng(5)
    t_moves = np.arange(10.0, 7200.0, 5.0)
    steps = np.cumsum(rng.normal(0.0, 0.3, size=(t_moves.size, 2)), axis=0) * 0.05
    steps += rng.normal(0.0, 0.4, size=steps.shape)
    h = History()
    h.add_events(
        [
            Event(float(t), EventKind.OFFSET_MOVE, *map(float, s))
            for t, s in zip(t_moves, steps, strict=True)
        ]
    )
    gain = np.array([1.0, 0.5])
    gaps = np.column_stack([play_gaps(steps[:, a], 2.0) for a in (0, 1)])
    t = np.arange(64.0, 7200.0, 64.0)
    k = np.searchsorted(t_moves, t, side="right") - 1
    xy = 0.01 * t[:, None] + gain[None, :] * np.where(k[:, None] >= 0, gaps[np.maximum(k, 0)], 0.0)
    xy += rng.normal(0.0, 0.1, size=xy.shape)
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "hysteresis"], residual="none"))
    _feed(model, t, xy, h, sigma_nm=0.1)
    play = model.offset_play()
    assert play is not None
    assert play.play_nm == pytest.approx(2.0, rel=0.15)
    assert play.gain == pytest.approx((1.0, 0.5), abs=0.1)


def test_no_offset_play_without_moves() -> None:
    t = np.arange(64.0, 3600.0, 64.0)
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "hysteresis"], residual="none"))
    _feed(model, t, np.column_stack([0.01 * t, 0.0 * t]), History())
    assert model.active == ["trend"]
    assert model.offset_play() is None


def test_a_loop_through_the_inverse_play_holds_the_image_on_a_simulated_scanner() -> None:
    """A closed loop on the simulator's scanner (a play of half-width 2 nm, and
    the drift term the simulator adds for it): commanding ``hold + d``
    directly lets the image jump by up to 4 nm each time the moves reverse;
    through :func:`offset_through_play`, with d(t) knowing the play only up to
    a few moves back (as a model fitted at the last frame does), it stays put.
    The simulator's scanner lags its command: gain −1."""
    from afmdrift.drivers.sim import SimulatedAFM

    rng = np.random.default_rng(2)
    drift = np.cumsum(rng.normal(0.0, 0.8, size=(400, 2)), axis=0)  # reverses often
    play, gain = 2.0, -1.0
    shown = {}
    for through in (False, True):
        physics = SimulatedAFM.from_scenario("default").physics
        sent = np.zeros(2)
        terms: list[np.ndarray] = []  # the simulator's hysteresis term after each move
        image = []
        for k, d_true in enumerate(drift):
            t = 10.0 + k
            # what d(t) knows: the drift and the play's term after the moves up to k - 5
            seen = terms[-5] if len(terms) >= 5 else np.zeros(2)
            want = d_true + seen
            cmd = np.array(want)
            if through:
                now = terms[-1] if terms else np.zeros(2)
                cmd = np.array(
                    [
                        offset_through_play(
                            float(want[a]),
                            sent=float(sent[a]),
                            gap_nm=float(now[a]) / gain,
                            gap_seen_nm=float(seen[a]) / gain,
                            play_nm=play,
                            gain=gain,
                        )
                        for a in (0, 1)
                    ]
                )
            physics.command_offset(t, float(cmd[0]), float(cmd[1]))
            sent = cmd
            terms.append(np.asarray(physics.components_at([t + 0.5])["hysteresis"][0]))
            # the image: the drift plus the simulator's hysteresis term, less the command
            image.append(d_true + terms[-1] - cmd)
        shown[through] = np.asarray(image)[20:]
    assert np.abs(shown[False]).max() > 2.0
    assert np.abs(shown[True]).max() < 1e-6


def test_commands_that_load_the_model_do_not_import_scipy_signal_or_optimize() -> None:
    """``afmdrift measure`` loads the model package: scipy.signal (0.8 s) and
    scipy.optimize (0.3 s) were imported with it, most of the command's
    start-up. The physics model imports scipy.optimize when it is made, and
    compiles the effect terms' kernels then (not at its first fit, in the
    middle of a daemon's run)."""
    import subprocess

    code = textwrap.dedent(
        """
        import sys, afmdrift.model, afmdrift.pipeline, afmdrift.cli._measure
        from afmdrift.model import _effects
        print(sorted(m for m in ("scipy.signal", "scipy.optimize") if m in sys.modules))
        print(len(_effects._first_order_lag.signatures), len(_effects._play_gaps.signatures))
        afmdrift.model.PhysicsPredictor()
        print(len(_effects._first_order_lag.signatures), len(_effects._play_gaps.signatures))
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.split("\n")[:3] == ["[]", "0 0", "1 1"]


@pytest.mark.parametrize("n", [1, 2, 7, 5000])
def test_first_order_lag_matches_its_recursion_exactly(n: int) -> None:
    """The thermal-lag filter (formerly ``scipy.signal.lfilter([1 − a], [1,
    −a], zi=[a·x₀])``) gives the same bits as that filter."""
    from scipy.signal import lfilter

    from afmdrift.model._effects import _first_order_lag

    rng = np.random.default_rng(n)
    values = np.cumsum(rng.standard_normal(n)) * 3.0 + 20.0
    for tau in (0.5, 30.0, 1e4):
        a = float(np.exp(-1.0 / tau))
        expected, _ = lfilter([1.0 - a], [1.0, -a], values, zi=np.array([a * values[0]]))
        np.testing.assert_array_equal(_first_order_lag(values, a), expected)


def test_scan_samples_cover_each_window_and_leave_points_alone() -> None:
    t = np.array([64.0, 320.0, 500.0])
    windows = np.array([[0.0, 128.0], [256.0, 384.0], [np.nan, np.nan]])
    s = scan_samples(t, windows, k=4)
    assert s.shape == (3, 4)
    np.testing.assert_allclose(s[0], [16.0, 48.0, 80.0, 112.0])
    np.testing.assert_allclose(s[1].mean(), 320.0)
    np.testing.assert_array_equal(s[2], 500.0)
    assert scan_samples(t).shape == (3, 1)


def test_a_frame_position_is_fitted_and_predicted_as_the_mean_over_its_scan() -> None:
    """A direct thermal response to a temperature that jitters within each
    2-min scan: the frame's position (the mean over its lines) differs from p
    at mid-scan by nanometres. With the scan windows, the model's one-step
    error is the measurement noise; taken as points, it is several times that."""
    rng = np.random.default_rng(5)
    tc = np.arange(0.0, 112 * PERIOD_S + 600.0, 10.0)
    temp = 22.0 + np.cumsum(rng.normal(0.0, 0.015, tc.size))
    history = History()
    for a, b in zip(tc, temp, strict=True):
        history.add_channels(ChannelSample(float(a), {"temperature_c": float(b)}))
    k_nm_per_k = np.array([-110.0, 40.0])

    def p(t: np.ndarray) -> np.ndarray:
        dt = np.interp(t, tc, temp) - temp[0]
        return 0.5 * t[:, None] / 3600.0 + dt[:, None] * k_nm_per_k[None, :]

    errors = {}
    for windowed in (True, False):
        model = PhysicsPredictor(PhysicsConfig(terms=["trend", "thermal"], residual="none"))
        err = []
        for i in range(112):
            t0 = i * PERIOD_S
            lines = t0 + (np.arange(512) + 0.5) * 0.25
            xy = p(lines).mean(axis=0) + rng.normal(0.0, 0.05, 2)
            obs = Observation(
                t0 + 64.0,
                float(xy[0]),
                float(xy[1]),
                0.05,
                ScanDirection.UP,
                i,
                window_s=(t0, t0 + 128.0) if windowed else None,
            )
            if i >= 20:
                pred, _ = model.predict_observation(obs, history)
                err.append(np.asarray([obs.x_nm, obs.y_nm]) - pred)
            model.update(obs, history)
        errors[windowed] = np.sqrt(np.mean(np.square(err), axis=0))
    assert np.all(errors[True] < 0.15), errors
    assert errors[False][0] > 3 * errors[True][0], errors


def test_one_step_prediction_takes_the_frame_s_own_scan_direction() -> None:
    """Directions in irregular runs (not alternating): the prediction of a
    frame must carry the bias of the direction it was scanned in, which is
    known when it is measured, not one extrapolated from the last frames."""
    rng = np.random.default_rng(2)
    n = 80
    runs = np.repeat(rng.integers(0, 2, size=n // 3 + 1), 3)[:n]
    dirs = [ScanDirection.UP if r else ScanDirection.DOWN for r in runs]
    t = PERIOD_S * np.arange(n) + 64.0
    bias = np.array([3.0, -2.0])
    sign = np.array([0.5 if d is ScanDirection.UP else -0.5 for d in dirs])
    xy = 0.8 * t[:, None] / 3600.0 + sign[:, None] * bias[None, :]
    xy += rng.normal(0.0, 0.05, xy.shape)
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "scan_direction"], residual="none"))
    err = []
    for i in range(n):
        obs = Observation(float(t[i]), float(xy[i, 0]), float(xy[i, 1]), 0.05, dirs[i], i)
        if i >= 20:
            pred, _ = model.predict_observation(obs, History())
            err.append(xy[i] - pred)
        model.update(obs, History())
    rms = np.sqrt(np.mean(np.square(err), axis=0))
    assert np.all(rms < 0.15), rms


def test_warmup_two_recovers_a_fast_and_a_slow_time_constant() -> None:
    history = History()
    history.add_events([Event(t_s=0.0, kind=EventKind.POWER_ON)])
    t = PERIOD_S * np.arange(112) + 64.0
    rng = np.random.default_rng(4)
    shape = np.column_stack([1 - np.exp(-t / 1500.0), 1 - np.exp(-t / 9000.0)])
    xy = shape @ np.array([[20.0, -8.0], [40.0, 25.0]]) + 0.4 * t[:, None] / 3600.0
    xy += rng.normal(0.0, 0.1, xy.shape)
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "warmup_two"], residual="none"))
    _feed(model, t, xy, history, sigma_nm=0.1)
    p = model.params["warmup_two"]
    assert p["tau_fast_s"] == pytest.approx(1500.0, rel=0.25)
    assert p["tau_slow_s"] == pytest.approx(9000.0, rel=0.35)


def test_a_new_event_s_response_is_fitted_from_its_first_frames_when_the_data_show_it() -> None:
    """One amplitude per event (``event:approach:each``): right after a new
    event its column is tiny on one or two frames. The model holds such a
    young column at 0 unless its amplitude is clearly determined (|β| ≥ 3σ);
    on clean data it is, so the new response is followed from its first
    frame (a fixed wait of three frames gave 5.0 nm here)."""
    history = History()
    events = [3000.0, 12000.0, 21000.0]
    history.add_events([Event(t_s=e, kind="approach") for e in events])
    amps = np.array([[10.0, -6.0], [-15.0, 9.0], [8.0, 12.0]])
    t = PERIOD_S * np.arange(110) + 64.0
    rng = np.random.default_rng(8)
    resp = np.zeros((t.size, 2))
    for e, a in zip(events, amps, strict=True):
        on = t > e
        resp[on] += (1 - np.exp(-(t[on] - e) / 1200.0))[:, None] * a[None, :]
    xy = 0.5 * t[:, None] / 3600.0 + resp + rng.normal(0.0, 0.1, resp.shape)
    model = PhysicsPredictor(PhysicsConfig(terms=["trend", "event:approach:each"], residual="none"))
    worst = 0.0
    for i in range(t.size):
        obs = Observation(float(t[i]), float(xy[i, 0]), float(xy[i, 1]), 0.1, ScanDirection.UP, i)
        if i >= 10 and any(0 < t[i] - e < 3 * PERIOD_S for e in events[1:]):
            pred, _ = model.predict_observation(obs, history)
            worst = max(worst, float(np.max(np.abs(xy[i] - pred))))
        model.update(obs, history)
    assert worst < 2.5, worst


@pytest.mark.parametrize(
    "spec", ["channel:laser_power_mw", "event:stage_move:each:tau_s=900", "event:approach:log"]
)
def test_a_generic_term_travels_by_pickle_as_its_spec(spec: str) -> None:
    # diagnose's online re-runs come back from other processes with their terms
    term = parse_term_spec(spec)()
    term.marker = 3  # type: ignore[attr-defined]
    back = pickle.loads(pickle.dumps(term))
    assert type(back) is type(term)
    assert back.name == spec
    assert back.marker == 3  # type: ignore[attr-defined]
