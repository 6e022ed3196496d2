"""Offset clamping (magnitude and rate), staleness, instrument clock, CURVE rule."""

from __future__ import annotations

import math

import pytest

from afmdrift.config import ServiceConfig, endpoint_is_local, parse_config
from afmdrift.errors import ConfigError
from afmdrift.service._safety import InstrumentClock, OffsetLimiter, is_stale


def test_magnitude_is_clamped_keeping_direction() -> None:
    lim = OffsetLimiter(max_offset_nm=10.0, max_rate_nm_s=1e9)
    out = lim.apply(0.0, 30.0, 40.0)
    assert out.clamped
    assert math.hypot(out.x_nm, out.y_nm) == pytest.approx(10.0)
    assert out.x_nm / out.y_nm == pytest.approx(0.75)


def test_rate_of_change_is_limited_per_instrument_second() -> None:
    lim = OffsetLimiter(max_offset_nm=1e6, max_rate_nm_s=2.0)
    lim.apply(0.0, 0.0, 0.0)
    out = lim.apply(0.5, 100.0, 0.0)  # wants 100 nm in 0.5 s
    assert out.clamped
    assert out.x_nm == pytest.approx(1.0)
    out = lim.apply(1.0, 100.0, 0.0)
    assert out.x_nm == pytest.approx(2.0)
    small = lim.apply(2.0, 3.0, 0.0)
    assert not small.clamped
    assert small.x_nm == 3.0


def test_non_finite_target_holds_previous_offset() -> None:
    """Regression guard: a NaN from a broken model must never reach the tip controller."""
    lim = OffsetLimiter(max_offset_nm=10.0, max_rate_nm_s=1.0)
    lim.apply(0.0, 1.0, 1.0)
    out = lim.apply(1.0, float("nan"), 0.0)
    assert out.clamped
    assert (out.x_nm, out.y_nm) == (1.0, 1.0)


def test_time_going_backwards_allows_no_jump() -> None:
    lim = OffsetLimiter(max_offset_nm=100.0, max_rate_nm_s=1.0)
    lim.apply(10.0, 0.0, 0.0)
    out = lim.apply(5.0, 50.0, 0.0)
    assert out.x_nm == 0.0
    assert out.clamped


def test_staleness_after_factor_times_expected_interval() -> None:
    kw = {"last_frame_t_s": 100.0, "expected_interval_s": 10.0, "factor": 2.0}
    assert not is_stale(now_s=119.0, **kw)
    assert is_stale(now_s=121.0, **kw)
    assert not is_stale(now_s=1e9, last_frame_t_s=None, expected_interval_s=10.0, factor=2.0)


def test_clock_estimates_rate_and_never_runs_backwards() -> None:
    clock = InstrumentClock()
    assert clock.at(0.0) is None
    clock.observe(wall_s=0.0, instrument_s=0.0)
    clock.observe(wall_s=1.0, instrument_s=50.0)
    assert clock.rate == pytest.approx(50.0)
    assert clock.at(1.1) == pytest.approx(55.0)
    clock.observe(wall_s=1.2, instrument_s=55.5)  # a late reading
    t = clock.at(1.15)
    assert t is not None
    assert t >= 55.0


@pytest.mark.parametrize(
    ("endpoint", "local"),
    [
        ("tcp://127.0.0.1:5560", True),
        ("tcp://127.3.2.1:1", True),
        ("tcp://localhost:5", True),
        ("tcp://[::1]:5560", True),
        ("ipc:///tmp/x", True),
        ("tcp://*:5560", False),
        ("tcp://0.0.0.0:5560", False),
        ("tcp://192.0.2.7:5560", False),
    ],
)
def test_endpoint_locality(endpoint: str, local: bool) -> None:
    assert endpoint_is_local(endpoint) is local


def test_binding_off_loopback_without_curve_keys_is_rejected() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"service": {"pub_endpoint": "tcp://*:5560"}}, source="s.toml")
    msg = str(info.value)
    assert "pub_endpoint" in msg
    assert "CURVE" in msg
    assert "service.curve_secret_key_file" in msg


def test_binding_off_loopback_with_curve_keys_is_accepted() -> None:
    cfg = ServiceConfig(
        pub_endpoint="tcp://*:5560",
        curve_secret_key_file="server.key_secret",
        curve_authorized_clients_dir="clients",
    )
    assert cfg.pub_endpoint == "tcp://*:5560"


def test_offset_rate_range_is_named() -> None:
    with pytest.raises(ConfigError, match=r"service.offset_rate_hz = 5000.*<= 1000"):
        parse_config({"service": {"offset_rate_hz": 5000}})
