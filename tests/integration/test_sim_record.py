"""``afmdrift sim record``: a recorded session round-trips through read_session."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from afmdrift.cli import main
from afmdrift.drivers import EventKind, ScanDirection
from afmdrift.drivers.sim import SimulatedAFM, load_scenario
from afmdrift.session import read_session

SMALL = """
name = "small"
duration_s = 900.0
seed = 4
[scan]
pixels = [32, 24]
size_nm = [128.0, 96.0]
line_rate_hz = 2.0
frame_period_s = 60.0
[sample]
map_px = 128
[physics.creep]
enabled = true
[physics.hysteresis]
enabled = true
play_nm = [2.0, 2.0]
[physics.scan_direction]
enabled = true
bias_nm = [0.5, 1.5]
[physics.random_walk]
enabled = true
sigma_nm_per_sqrt_s = [0.05, 0.05]
[physics.tip_changes]
enabled = true
scheduled = [{ t_s = 500.0, step_nm = [3.0, 1.0] }]
[[offset_moves]]
t_s = 200.0
x_nm = 40.0
y_nm = -10.0
[[manipulations]]
t_s = 300.0
x0_nm = 60.0
y0_nm = 40.0
x1_nm = 80.0
y1_nm = 40.0
"""


@pytest.fixture
def scenario_file(tmp_path: Path) -> Path:
    p = tmp_path / "small.toml"
    p.write_text(SMALL)
    return p


def test_record_round_trips_through_read_session(
    scenario_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "rec"
    assert main(["sim", "record", str(scenario_file), "--out", str(out)]) == 0
    assert "15 frames" in capsys.readouterr().out
    s = read_session(out)
    assert len(s) == 15
    assert s.frames.shape == (15, 24, 32)
    assert s.meta.pixel_size_nm == (4.0, 4.0)
    assert s.meta.line_time_s == 0.5
    assert s.directions[:2] == [ScanDirection.UP, ScanDirection.DOWN]
    assert s.meta.extra["simulator"]["scan_direction_bias_nm"] == [0.5, 1.5]
    kinds = [e.kind for e in s.events]
    assert kinds == [
        EventKind.POWER_ON,
        EventKind.OFFSET_MOVE,
        EventKind.MANIPULATION,
        EventKind.TIP_CHANGE,
    ]
    assert s.events[0].t_s == 0.0
    assert set(s.channels) == {"temperature_c", "humidity_pct"}
    assert s.channel_t_s[-1] == pytest.approx(900.0)
    assert s.truth is not None
    # truth.csv is the simulator's p(t), exactly (same seed, same schedule).
    sim = SimulatedAFM.from_scenario(scenario_file)
    sim.advance_to(900.0)
    tx, ty = sim.truth_at(s.truth[:, 0])
    np.testing.assert_allclose(s.truth[:, 1], tx, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.truth[:, 2], ty, rtol=0, atol=1e-12)
    # Frames equal the live simulator's frames.
    np.testing.assert_allclose(
        s.frames[-1],
        sim.latest_frame().heights_nm,
        atol=1e-5,  # type: ignore[union-attr]
    )
    with (out / "truth_components.csv").open() as fh:
        header = next(csv.reader(fh))
    assert "creep_x_nm" in header
    assert "hysteresis_y_nm" in header
    doc = json.loads((out / "scenario.json").read_text())
    assert doc["seed"] == 4


def test_record_is_deterministic_by_seed(scenario_file: Path, tmp_path: Path) -> None:
    for name, seed in (("a", "1"), ("b", "1"), ("c", "2")):
        args = ["sim", "record", str(scenario_file), "--out", str(tmp_path / name)]
        assert main([*args, "--seed", seed, "--frames", "3"]) == 0
    a, b, c = (read_session(tmp_path / n) for n in "abc")
    assert len(a) == 3
    np.testing.assert_array_equal(a.frames, b.frames)
    np.testing.assert_array_equal(a.truth, b.truth)  # type: ignore[arg-type]
    np.testing.assert_array_equal(a.channels["temperature_c"], b.channels["temperature_c"])
    assert not np.array_equal(a.frames, c.frames)


def test_bad_scenario_exits_2_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[scan]\nline_rate_hz = 0\n")
    assert main(["sim", "record", str(bad), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "scan.line_rate_hz = 0" in err
    assert "Traceback" not in err


def test_no_complete_frame_is_an_error(
    scenario_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["sim", "record", str(scenario_file), "--out", str(tmp_path / "x"), "--duration-s", "5"]
    assert main(args) == 2
    assert "no frame completed" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize(
    "name", ["default", "graphite-paper", "gold-manipulation-8h", "quiet-lab-24h", "hsafm-movie"]
)
def test_built_in_scenarios_record_a_few_frames(name: str, tmp_path: Path) -> None:
    out = tmp_path / name
    assert main(["sim", "record", name, "--out", str(out), "--frames", "2"]) == 0
    s = read_session(out)
    sc = load_scenario(name)
    assert s.frames.shape == (2, sc.scan.pixels[1], sc.scan.pixels[0])
    assert np.isfinite(s.frames).all()
    assert s.frames[0].std() > 0.05


def test_unwritable_output_is_an_error_not_a_traceback(
    scenario_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    args = ["sim", "record", str(scenario_file), "--out", str(blocker), "--frames", "1"]
    assert main(args) == 2
    assert "cannot write the session" in capsys.readouterr().err
