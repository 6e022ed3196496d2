"""Wire format v1: every schema round-trips, and bad messages are rejected clearly."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from afmdrift.wire import (
    SCHEMA_VERSION,
    ClockSync,
    ControlReply,
    ControlRequest,
    DiagnosisMsg,
    FieldSummary,
    FrameMsg,
    ModelMsg,
    OffsetMsg,
    Published,
    StatusMsg,
    WireError,
    decode,
    decode_control_reply,
    decode_control_request,
    encode,
)

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


def _examples() -> list[Published]:
    clock = ClockSync(wall_s=1.7e9, instrument_s=12.5, rate=40.0)
    return [
        OffsetMsg(seq=3, t_s=12.5, wall_s=1.7e9, x_nm=1.25, y_nm=-0.5, valid=True),
        ModelMsg(
            seq=1,
            frame=4,
            t_s=100.0,
            wall_s=1.7e9,
            predictor="physics",
            curve={"kind": "hermite", "t_s": [1.0, 2.0], "x_nm": [0.0, 1.0]},
            clock=clock,
            max_offset_nm=5000.0,
            max_offset_rate_nm_s=5.0,
        ),
        FrameMsg(
            seq=2,
            frame=4,
            instrument_frame=7,
            t_s=100.0,
            wall_s=1.7e9,
            dx_nm=0.1,
            dy_nm=None,
            x_nm=3.0,
            y_nm=None,
            sigma_nm=0.2,
            valid=False,
            fed_model=False,
            reason="nan in frame",
            valid_blocks=0,
            total_blocks=16,
            field=FieldSummary(
                total_blocks=16,
                valid_blocks=0,
                mean_dx_nm=None,
                mean_dy_nm=None,
                std_dx_nm=None,
                std_dy_nm=None,
                median_confidence=None,
            ),
            pred_x_nm=None,
            pred_y_nm=None,
            pred_error_nm=None,
            latency_s=0.01,
        ),
        StatusMsg(
            seq=9,
            t_s=None,
            wall_s=1.7e9,
            state="stale",
            flags=["stale", "no_model"],
            frames=0,
            last_frame_t_s=None,
            expected_frame_interval_s=None,
            rolling_error_nm=None,
            rolling_max_error_nm=None,
            rolling_window=20,
        ),
        DiagnosisMsg(
            seq=0,
            wall_s=1.7e9,
            look=3,
            first_frame=0,
            last_frame=29,
            reason="every",
            duration_s=4.5,
            diagnosis={"schema_version": 1, "plain_finding": "Nothing is missing.", "tests": 12},
        ),
    ]


@pytest.mark.parametrize("msg", _examples(), ids=lambda m: m.topic)
def test_every_topic_round_trips(msg: Published) -> None:
    parts = encode(msg)
    assert parts[0] == msg.topic.encode()
    assert json.loads(parts[1])["v"] == SCHEMA_VERSION
    assert decode(parts) == msg


@given(seq=st.integers(0, 2**62), t=finite, x=finite, y=finite, valid=st.booleans())
def test_offset_round_trips_any_finite_value(
    seq: int, t: float, x: float, y: float, valid: bool
) -> None:
    msg = OffsetMsg(seq=seq, t_s=t, wall_s=t, x_nm=x, y_nm=y, valid=valid)
    assert decode(encode(msg)) == msg


def test_other_schema_version_is_rejected_with_both_versions_named() -> None:
    parts = encode(_examples()[0])
    doc = json.loads(parts[1])
    doc["v"] = 2
    with pytest.raises(WireError, match=r"version 2 .* speaks 1"):
        decode([parts[0], json.dumps(doc).encode()])


def test_topic_payload_mismatch_is_rejected() -> None:
    parts = encode(_examples()[0])
    with pytest.raises(WireError, match="carries a payload for topic 'offset'"):
        decode([b"status", parts[1]])


@pytest.mark.parametrize(
    ("parts", "match"),
    [
        ([b"offset"], "2 message parts"),
        ([b"nope", b"{}"], "unknown topic"),
        ([b"offset", b"\xff\xfe"], "not JSON"),
        ([b"offset", b"[1, 2]"], "JSON object"),
        ([b"offset", b'{"v": 1, "topic": "offset", "seq": -1}'], "invalid payload"),
    ],
)
def test_malformed_messages_raise_wire_error(parts: list[bytes], match: str) -> None:
    with pytest.raises(WireError, match=match):
        decode(parts)


def test_clock_sync_maps_wall_to_instrument_time() -> None:
    clock = ClockSync(wall_s=100.0, instrument_s=50.0, rate=10.0)
    assert clock.instrument_at(101.5) == pytest.approx(65.0)


def test_control_messages_round_trip() -> None:
    req = ControlRequest(cmd="reload_model", config_path="x.toml")
    assert decode_control_request(req.model_dump_json().encode()) == req
    status = _examples()[3]
    assert isinstance(status, StatusMsg)
    rep = ControlReply(ok=True, status=status)
    assert decode_control_reply(rep.model_dump_json().encode()) == rep
    with pytest.raises(WireError, match="control request"):
        decode_control_request(b'{"v": 1, "cmd": "format_disk"}')
