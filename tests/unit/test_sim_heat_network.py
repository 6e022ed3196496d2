"""The second physics (``physics.model = "heat_network"``, docs/physics.md): its
equations, its sign conventions and the shipped ``heat-network-2h`` scenario."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
from scipy.integrate import solve_ivp

from afmdrift.drivers.sim import (
    HEAT_NETWORK_COMPONENTS,
    DriftPhysics,
    HeatNetworkPhysics,
    SimulatedAFM,
    load_scenario,
    make_physics,
    parse_scenario,
)
from afmdrift.drivers.sim._record import record_session
from afmdrift.drivers.sim._scenario import PhysicsConfig
from afmdrift.errors import ConfigError
from afmdrift.session import read_session

TWO_HOURS = np.arange(0.0, 7200.0 + 1e-9, 1.0)


def _shipped() -> HeatNetworkPhysics:
    sc = load_scenario("heat-network-2h")
    physics = make_physics(sc.physics, seed=sc.seed)
    assert isinstance(physics, HeatNetworkPhysics)
    return physics


def _config(**heat_network: Any) -> PhysicsConfig:
    return PhysicsConfig.model_validate({"model": "heat_network", "heat_network": heat_network})


def test_the_shipped_scenario_loads_with_256_lines_of_half_a_second_back_to_back() -> None:
    sc = load_scenario("heat-network-2h")
    assert sc.physics.model == "heat_network"
    assert sc.scan.pixels[1] == 256
    assert sc.scan.line_rate_hz == 2.0
    assert sc.scan.frame_period_s is None  # back to back: 128 s per frame
    sim = SimulatedAFM(sc)
    assert isinstance(sim.physics, HeatNetworkPhysics)
    assert sim.frame_period_s == pytest.approx(128.0)


def test_the_same_seed_gives_the_same_drift_however_time_is_asked() -> None:
    cfg = load_scenario("heat-network-2h").physics
    a = HeatNetworkPhysics(cfg, seed=11)
    b = HeatNetworkPhysics(cfg, seed=11)
    t = np.linspace(0.0, 7200.0, 997)
    whole = a.drift_at(t)
    backwards = b.drift_at(t[::-1])[::-1]
    np.testing.assert_array_equal(whole, backwards)
    np.testing.assert_allclose(a.drift_at(float(t[500])), whole[500], rtol=0, atol=1e-12)
    other = HeatNetworkPhysics(cfg, seed=12).drift_at(t)
    assert np.abs(other - whole).max() > 1.0  # the wander differs by seed
    np.testing.assert_array_equal(a.drift_at(0.0), [0.0, 0.0])


def test_uncompensated_drift_is_at_least_100_nm_rms_over_two_hours() -> None:
    """Issue 39: at least as hard as the independent instrument (135.5 nm RMS),
    relative to the first frame (mid-time 64 s), for the scenario's seed and others."""
    sc = load_scenario("heat-network-2h")
    for seed in (sc.seed, 1, 2, 5):
        p = make_physics(sc.physics, seed=seed).drift_at(TWO_HOURS)
        r = np.hypot(*(p - p[64]).T)
        assert np.sqrt(np.mean(r**2)) >= 100.0, seed


def test_the_room_cycle_reverses_and_each_node_lags_the_one_before() -> None:
    physics = _shipped()
    air = physics.head_temperature_c(TWO_HOURS)
    slope_signs = np.sign(np.diff(air))
    reversals = np.count_nonzero(np.diff(slope_signs[slope_signs != 0]))
    assert reversals >= 2  # heats, cools, heats again within 2 h
    assert air.max() - air.min() == pytest.approx(1.0, abs=1e-6)  # the ±0.5 K band
    stage = physics.stage_temperature_c(TWO_HOURS)
    scanner = physics.scanner_temperature_c(TWO_HOURS)
    # the first maximum of each node comes later down the chain
    first_peak = [int(np.argmax(np.diff(x) < 0)) for x in (air, stage, scanner)]
    assert first_peak[0] < first_peak[1] < first_peak[2]


def test_the_closed_form_nodes_match_a_numerical_integration() -> None:
    cfg = _config(stage_offset_k=-0.3, tau_stage_s=700.0, tau_scanner_s=1900.0)
    physics = HeatNetworkPhysics(cfg, seed=0)
    t = np.linspace(0.0, 9000.0, 301)
    stage = physics.stage_temperature_c(t)
    scanner = physics.scanner_temperature_c(t)

    def rhs(tt: float, y: npt.NDArray[np.float64]) -> list[float]:
        air = float(physics.head_temperature_c(tt))
        return [(air - y[0]) / 700.0, (y[0] - y[1]) / 1900.0]

    sol = solve_ivp(
        rhs, (0.0, 9000.0), [21.7, 21.7], t_eval=t, rtol=1e-9, atol=1e-10, max_step=20.0
    )
    np.testing.assert_allclose(stage, sol.y[0], atol=1e-5)
    np.testing.assert_allclose(scanner, sol.y[1], atol=1e-5)


def test_warmup_is_algebraic_half_way_at_its_time_constant() -> None:
    physics = HeatNetworkPhysics(_config(warmup_nm=(80.0, -100.0), warmup_tau_s=1500.0), seed=0)
    w = physics.components_at(np.array([1500.0, 4500.0]))["warmup"]
    np.testing.assert_allclose(w[0], [40.0, -50.0], rtol=1e-12)
    np.testing.assert_allclose(w[1], [60.0, -75.0], rtol=1e-12)  # t/(t+τ), not 1 − e^(−t/τ)


def test_axes_are_coupled_and_the_components_sum_to_the_drift() -> None:
    physics = HeatNetworkPhysics(
        _config(warmup_nm=(100.0, 0.0), cross_coupling=(0.2, -0.15)), seed=0
    )
    comps = physics.components_at(TWO_HOURS)
    assert tuple(comps) == HEAT_NETWORK_COMPONENTS
    np.testing.assert_allclose(comps["warmup"][:, 1], -0.15 * comps["warmup"][:, 0], atol=1e-12)
    np.testing.assert_allclose(sum(comps.values()), physics.drift_at(TWO_HOURS), atol=1e-12)


def test_a_commanded_move_or_compensation_ramp_is_not_drift() -> None:
    """docs/physics.md sign convention: a move of +Δ moves the window by +Δ (features
    appear at u − Δ) and is not part of p(t); this model adds no creep or play."""
    physics = _shipped()
    twin = _shipped()
    physics.command_offset(100.0, 30.0, -20.0)
    physics.ramp_compensation(200.0, (0.5, -0.25), (1000.0, 1000.0))
    t = np.array([50.0, 150.0, 300.0, 7000.0])
    np.testing.assert_array_equal(physics.drift_at(t), twin.drift_at(t))
    np.testing.assert_allclose(physics.scan_offset_at(t[:3]), [[0, 0], [30, -20], [80, -45]])
    assert [(m.dx_nm, m.dy_nm, m.ex_nm, m.ey_nm) for m in physics.moves] == [(30, -20, 0, 0)]
    # image content p − o moves opposite to the command
    c = physics.drift_at(t) - physics.scan_offset_at(t)
    c_twin = twin.drift_at(t) - twin.scan_offset_at(t)
    np.testing.assert_allclose(c[1] - c_twin[1], [-30.0, 20.0])


def test_the_controller_holds_its_displacement_when_the_velocity_changes() -> None:
    physics = _shipped()
    physics.ramp_compensation(100.0, (1.0, -0.5), (1000.0, 1000.0))
    held = physics.ramp_compensation(300.0, (0.0, 0.0), (1000.0, 1000.0))
    np.testing.assert_allclose(held, [200.0, -100.0])
    np.testing.assert_allclose(physics.compensation_at(np.array([300.0, 5000.0])), [held, held])


def test_a_tip_change_is_a_step_in_the_drift() -> None:
    physics = _shipped()
    twin = _shipped()
    physics.add_tip_change(500.0, 4.0, -3.0)
    t = np.array([499.0, 501.0])
    np.testing.assert_allclose(physics.drift_at(t) - twin.drift_at(t), [[0, 0], [4, -3]])


def test_logged_humidity_follows_the_air_and_there_are_no_extra_channels() -> None:
    physics = _shipped()
    t = np.array([0.0, 900.0])
    air = physics.head_temperature_c(t)
    np.testing.assert_allclose(air, [22.0, 22.5])
    np.testing.assert_allclose(physics.humidity_pct(t), [45.0, 45.0 - 2.7 * 0.5])
    assert physics.channel_values(t) == {}


def test_a_wrong_model_name_is_refused_naming_the_key_and_the_choices() -> None:
    with pytest.raises(ConfigError) as err:
        parse_scenario({"physics": {"model": "room"}}, source="s.toml")
    msg = str(err.value)
    assert "s.toml: physics.model = 'room'" in msg
    assert "'effects', 'heat_network'" in msg


@pytest.mark.parametrize(
    ("physics", "words"),
    [
        ({"model": "heat_network", "thermal": {"enabled": True}}, "does not read physics.thermal"),
        ({"heat_network": {"band_k": 1.0}}, "only with physics.model = 'heat_network'"),
        (
            {"model": "heat_network", "heat_network": {"tau_stage_s": 600, "tau_scanner_s": 600}},
            "tau_scanner_s = 600.0 must differ",
        ),
        (
            {"model": "heat_network", "heat_network": {"cross_coupling": [1.5, 0]}},
            "cross_coupling k_xy = 1.5 is out of range",
        ),
    ],
)
def test_tables_the_model_does_not_read_and_bad_values_are_refused(
    physics: dict[str, Any], words: str
) -> None:
    with pytest.raises(ConfigError, match=words):
        parse_scenario({"physics": physics}, source="s.toml")


def test_the_default_model_is_still_the_sum_of_effects() -> None:
    assert isinstance(make_physics(PhysicsConfig(), seed=0), DriftPhysics)


def test_a_recorded_session_carries_the_heat_network_components(tmp_path: Path) -> None:
    data = {
        "scan": {"pixels": [16, 16], "size_nm": [64.0, 64.0], "line_rate_hz": 1.0},
        "sample": {"map_px": 128, "grid_nm": 4.0},
        "physics": {"model": "heat_network", "heat_network": {"warmup_nm": [50.0, 20.0]}},
    }
    out = tmp_path / "session"
    record_session(parse_scenario(data), out, seed=1, duration_s=40.0)
    with (out / "truth_components.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["t_s"] + [f"{c}_{a}_nm" for c in HEAT_NETWORK_COMPONENTS for a in "xy"]
    values = np.array(rows[1:], dtype=np.float64)
    truth = read_session(out).truth
    assert truth is not None
    np.testing.assert_allclose(values[:, 1::2].sum(axis=1), truth[:, 1], atol=1e-9)
    np.testing.assert_allclose(values[:, 2::2].sum(axis=1), truth[:, 2], atol=1e-9)
