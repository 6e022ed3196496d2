"""SimulatedAFM: clock, frames, geometry, events, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from afmdrift.drivers import EventKind, ScanDirection
from afmdrift.drivers.sim import Scenario, SimulatedAFM, parse_scenario


def small_scenario(**overrides: object) -> Scenario:
    data: dict[str, object] = {
        "scan": {"pixels": [64, 48], "size_nm": [256.0, 192.0], "line_rate_hz": 16.0},
        "sample": {"map_px": 256, "grid_nm": 4.0, "gold": {"density_per_um2": 40.0}},
        "physics": {"random_walk": {"enabled": True, "sigma_nm_per_sqrt_s": [0.5, 0.5]}},
    }
    data.update(overrides)
    return parse_scenario(data)


def test_frames_complete_back_to_back_alternating() -> None:
    sim = SimulatedAFM(small_scenario(), seed=1)
    assert sim.latest_frame() is None
    frames = sim.advance_to(3 * 3.0 + 0.5)  # 48 lines at 16 Hz = 3 s per frame
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.direction for f in frames] == [ScanDirection.UP, ScanDirection.DOWN] * 1 + [
        ScanDirection.UP
    ]
    assert frames[1].t_start_s == pytest.approx(frames[0].t_end_s)
    f = sim.latest_frame()
    assert f is frames[-1]
    assert f.heights_nm.shape == (48, 64)
    assert f.pixel_size_nm == (4.0, 4.0)
    assert np.isfinite(f.heights_nm).all()


def test_same_seed_same_session_different_seed_differs() -> None:
    a = SimulatedAFM(small_scenario(), seed=5)
    b = SimulatedAFM(small_scenario(), seed=5)
    c = SimulatedAFM(small_scenario(), seed=6)
    fa = a.advance_to(10.0)
    # Same time reached in different steps: determinism must not depend on the call pattern.
    for t in (1.3, 2.9, 7.7, 10.0):
        fb = b.advance_to(t)
    fc = c.advance_to(10.0)
    np.testing.assert_array_equal(fa[-1].heights_nm, b.latest_frame().heights_nm)  # type: ignore[union-attr]
    assert fb[-1].index == fa[-1].index
    assert not np.allclose(fa[-1].heights_nm, fc[-1].heights_nm)
    t = np.linspace(0, 10, 11)
    np.testing.assert_array_equal(a.truth_at(t)[0], b.truth_at(t)[0])


def test_offset_move_is_logged_with_delta_and_not_in_truth() -> None:
    sim = SimulatedAFM(small_scenario(physics={}), seed=0)
    sim.advance_to(1.0)
    sim.set_offset(100.0, -20.0)
    sim.advance_to(2.0)
    sim.set_offset(150.0, -20.0)
    kinds = [e.kind for e in sim.events]
    assert kinds == [EventKind.POWER_ON, EventKind.OFFSET_MOVE, EventKind.OFFSET_MOVE]
    assert (sim.events[2].x_nm, sim.events[2].y_nm) == (50.0, 0.0)
    assert sim.get_offset() == (150.0, -20.0)
    assert sim.truth_at(5.0) == (0.0, 0.0)


def test_configure_scan_rejects_out_of_range_with_message() -> None:
    sim = SimulatedAFM(small_scenario(), seed=0)
    with pytest.raises(ValueError, match="pixels cols = 4"):
        sim.configure_scan(pixels=(4, 64))
    with pytest.raises(ValueError, match="line_rate_hz = -1"):
        sim.configure_scan(line_rate_hz=-1.0)
    sim.configure_scan(pixels=(32, 32), size_nm=(128.0, 128.0), line_rate_hz=32.0)
    frames = sim.advance_to(1.01)
    assert frames[-1].heights_nm.shape == (32, 32)


def test_time_cannot_go_back() -> None:
    sim = SimulatedAFM(small_scenario(), seed=0)
    sim.advance_to(5.0)
    with pytest.raises(ValueError, match="advance_to"):
        sim.advance_to(4.0)


def test_stop_abandons_frame_and_start_restarts_up() -> None:
    sim = SimulatedAFM(small_scenario(), seed=0)
    sim.advance_to(4.0)  # frame 0 done, frame 1 (down) in progress
    sim.stop()
    assert not sim.running
    assert sim.advance_to(20.0) == []
    sim.start()
    frames = sim.advance_to(23.5)
    assert frames[0].index == 1
    assert frames[0].direction is ScanDirection.UP
    assert frames[0].t_start_s == pytest.approx(20.0)


def test_channels_and_identify() -> None:
    sim = SimulatedAFM(small_scenario(), seed=0)
    sim.advance_to(10.0)
    ch = sim.read_channels()
    assert ch.t_s == 10.0
    assert set(ch.values) == {"temperature_c", "humidity_pct"}
    assert abs(ch.values["temperature_c"] - 22.0) < 1.0
    info = sim.identify()
    assert info.model == "SimulatedAFM"


def test_jumping_ahead_without_rendering_superseded_frames_gives_the_same_latest_frame() -> None:
    a = SimulatedAFM(small_scenario(), seed=3)
    b = SimulatedAFM(small_scenario(), seed=3)
    all_frames = a.advance_to(100.0)
    few = b.advance_to(100.0, render_all=False)
    assert len(all_frames) == 33
    assert [f.index for f in few] == [32]
    np.testing.assert_array_equal(few[0].heights_nm, all_frames[-1].heights_nm)
    assert b.latest_frame().index == a.latest_frame().index  # type: ignore[union-attr]
    # And the next frames stay identical.
    np.testing.assert_array_equal(
        a.advance_to(104.0)[0].heights_nm, b.advance_to(104.0)[0].heights_nm
    )


def test_random_api_sequences_never_break_the_clock_or_the_frames() -> None:
    """Guards the long-running server: any interleaving of commands keeps frames
    complete, ordered and inside their own scan interval."""
    rng = np.random.default_rng(11)
    sc = small_scenario(
        physics={
            "creep": {"enabled": True},
            "hysteresis": {"enabled": True, "play_nm": [1.0, 1.0]},
            "tip_changes": {"enabled": True, "rate_per_h": 100.0},
        }
    )
    sim = SimulatedAFM(sc, seed=2)
    last_index = -1
    for _ in range(300):
        op = int(rng.integers(0, 6))
        if op == 0:
            sim.set_offset(*rng.normal(0.0, 50.0, 2))
        elif op == 1:
            sim.configure_scan(pixels=(int(rng.integers(8, 40)), int(rng.integers(8, 40))))
        elif op == 2:
            sim.stop()
        elif op == 3:
            sim.start()
        elif op == 4:
            sim.manipulate(*rng.uniform(0.0, 150.0, 4))
        t_next = sim.now_s + float(rng.exponential(2.0))
        for f in sim.advance_to(t_next, render_all=bool(rng.integers(0, 2))):
            assert f.index > last_index
            last_index = f.index
            assert f.t_start_s < f.t_end_s <= t_next
            assert np.isfinite(f.heights_nm).all()
            assert f.heights_nm.shape == (f.shape[0], f.shape[1])
    times = [e.t_s for e in sim.events]
    assert times == sorted(times)
    assert sim.now_s > 100.0
