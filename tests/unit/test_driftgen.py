"""The second drift-log generator: deterministic, read as any drift log, and
different from the simulator where it says it is."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from afmdrift.session import read_drift_log
from afmdrift.testing import (
    DRIFTGEN_EFFECTS,
    DRIFTGEN_SHAPES,
    GeneratedLog,
    generate_drift_log,
    write_drift_log,
)


@pytest.mark.parametrize("effect", DRIFTGEN_EFFECTS)
def test_a_generated_log_is_read_back_as_written(effect: str, tmp_path: Path) -> None:
    gen = generate_drift_log(effect, 3)
    log = read_drift_log(write_drift_log(gen, tmp_path / effect))
    assert len(log) == gen.t_s.size == 112
    np.testing.assert_array_equal(log.xy_nm, gen.xy_nm)
    np.testing.assert_array_equal(log.frame_times, gen.frame_times)
    assert log.truth is not None
    assert set(log.channels) == {"temperature_c", "humidity_pct", "pressure_hpa"}
    answer = json.loads((tmp_path / effect / "answer.json").read_text())
    assert answer["hidden_effect"] == effect
    kinds = {str(e.kind) for e in log.events}
    assert ("power_on" in kinds) == (effect == "warmup")
    assert {"manipulation", "offset_move", "approach"} <= kinds


def test_the_generator_is_deterministic_and_seeds_differ() -> None:
    a, b = generate_drift_log("creep", 1), generate_drift_log("creep", 1)
    np.testing.assert_array_equal(a.xy_nm, b.xy_nm)
    c = generate_drift_log("creep", 2)
    assert not np.allclose(a.xy_nm, c.xy_nm)


def _scan_means(gen: GeneratedLog) -> np.ndarray:
    """The true drift averaged over each frame's scan window."""
    lines = np.linspace(gen.frame_times[:, :1], gen.frame_times[:, 1:], 200, axis=1)[..., 0]
    return np.column_stack(
        [np.interp(lines, gen.truth_t_s, gen.truth_nm[:, a]).mean(axis=1) for a in (0, 1)]
    )


def test_positions_follow_the_truth_within_the_measurement_noise() -> None:
    gen = generate_drift_log("thermal_lag", 5)
    truth = _scan_means(gen)
    err = gen.xy_nm[1:] - truth[1:]
    assert np.std(err) == pytest.approx(gen.sigma_nm, rel=0.3)
    assert np.ptp(truth[:, 0]) > 10 * gen.sigma_nm  # a drift worth measuring


def test_a_scan_direction_log_has_runs_of_both_directions_and_a_bias() -> None:
    gen = generate_drift_log("scan_direction", 4)
    assert {"up", "down"} <= set(gen.directions)
    up = np.array([d == "up" for d in gen.directions])
    truth = _scan_means(gen)
    bias = (gen.xy_nm - truth)[up].mean(axis=0) - (gen.xy_nm - truth)[~up].mean(axis=0)
    assert np.hypot(*bias) > 0.9  # at least 1 nm between the directions, less the noise


def test_an_unknown_effect_is_refused() -> None:
    with pytest.raises(ValueError, match="effect must be one of"):
        generate_drift_log("gravity", 1)


@pytest.mark.parametrize("shape", DRIFTGEN_SHAPES)
def test_a_hidden_shape_is_in_the_truth_and_in_the_answer(shape: str) -> None:
    """The control's drift plus the shape: the truth differs from the control
    of the same seed by the shape alone, which answer.json describes."""
    log = generate_drift_log(shape, 3)
    found = log.answer["shape"]
    assert found["kind"] in ("periodic", "jump", "rate_change")
    assert log.answer["hidden_effect"] == shape
    t = log.truth_t_s
    if found["kind"] == "jump":
        before = np.interp(found["t_start_s"] - 60.0, t, log.truth_nm[:, 0])
        after = np.interp(found["t_end_s"] + 60.0, t, log.truth_nm[:, 0])
        assert abs(after - before) > 0.0
        assert 8.0 <= found["step_nm"] <= 20.0
    elif found["kind"] == "periodic":
        assert 1200.0 <= found["period_s"] <= 2400.0
    else:
        assert 20.0 <= found["rate_change_nm_per_h"] <= 60.0
