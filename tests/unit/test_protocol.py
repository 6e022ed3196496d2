"""The pure protocol codec: commands, replies, frame blocks, and fuzzing of the parsers."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from afmdrift.drivers import ChannelSample, Event, EventKind, Frame, ScanDirection
from afmdrift.drivers._protocol import (
    COMMANDS,
    ChecksumError,
    Command,
    CommandError,
    InstrumentError,
    OutOfSequenceError,
    ProtocolError,
    args_count_ok,
    check_header,
    decode_channels,
    decode_event,
    decode_frame_reply,
    encode_channels,
    encode_command,
    encode_error,
    encode_event,
    encode_frame_reply,
    encode_no_frame,
    encode_ok,
    encode_value,
    parse_args_floats,
    parse_command,
    parse_error_body,
    parse_reply,
)


def _frame(rows: int = 8, cols: int = 6, dtype: type = np.float32, index: int = 4) -> Frame:
    rng = np.random.default_rng(index)
    return Frame(
        index=index,
        heights_nm=rng.normal(size=(rows, cols)).astype(dtype),
        pixel_size_nm=(3.90625, 4.0),
        t_start_s=256.0 * index,
        t_end_s=256.0 * index + 128.0,
        direction=ScanDirection.DOWN if index % 2 else ScanDirection.UP,
    )


# --------------------------------------------------------------------------- commands


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        (b"*IDN?\n", Command("*IDN", True)),
        (b"@12 scan:size? \r\n", Command("SCAN:SIZE", True, tag=12)),
        (b"SCAN:OFFS 1.5, -2e3\n", Command("SCAN:OFFS", False, ("1.5", "-2e3"))),
        (b"@0 EVENT:LOG? 3", Command("EVENT:LOG", True, ("3",), tag=0)),
        (b"TIP:MAN 1,2,3,4\n", Command("TIP:MAN", False, ("1", "2", "3", "4"))),
    ],
)
def test_parse_command_accepts_valid_lines(line: bytes, expected: Command) -> None:
    assert parse_command(line) == expected


@pytest.mark.parametrize(
    ("line", "code"),
    [
        (b"\n", -102),
        (b"SCAN:SIZE 1,,2\n", -102),
        (b"SCAN:\xffSIZE?\n", -101),
        (b"@x SCAN:SIZE?\n", -101),
        (b"A" * 5000 + b"\n", -363),
        (b"1ABC?\n", -102),
    ],
)
def test_parse_command_rejects_bad_lines_with_scpi_code(line: bytes, code: int) -> None:
    with pytest.raises(CommandError) as info:
        parse_command(line)
    assert info.value.code == code


def test_encode_command_round_trips_through_parse_command() -> None:
    data = encode_command("SCAN:OFFS", 12.25, -3.0, tag=99)
    assert data == b"@99 SCAN:OFFS 12.25,-3.0\n"
    assert parse_command(data) == Command("SCAN:OFFS", False, ("12.25", "-3.0"), tag=99)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), "a,b", "x y", True])
def test_encode_command_refuses_unsendable_arguments(bad: object) -> None:
    with pytest.raises(ValueError, match=r"argument|finite|boolean"):
        encode_command("SCAN:RATE", bad)  # type: ignore[arg-type]


def test_argument_counts_follow_the_command_table() -> None:
    assert args_count_ok(COMMANDS["SCAN:SIZE"], Command("SCAN:SIZE", True)) is None
    assert args_count_ok(COMMANDS["SCAN:SIZE"], Command("SCAN:SIZE", False, ("1",)))[0] == -109  # type: ignore[index]
    assert args_count_ok(COMMANDS["SCAN:RATE"], Command("SCAN:RATE", False, ("1", "2")))[0] == -108  # type: ignore[index]
    assert args_count_ok(COMMANDS["SCAN:START"], Command("SCAN:START", True))[0] == -113  # type: ignore[index]


def test_numeric_arguments_are_checked() -> None:
    assert parse_args_floats(Command("SCAN:OFFS", False, ("1", "-2.5e1"))) == (1.0, -25.0)
    with pytest.raises(CommandError) as info:
        parse_args_floats(Command("SCAN:OFFS", False, ("1", "nan")))
    assert info.value.code == -104
    with pytest.raises(CommandError) as info:
        parse_args_floats(Command("SCAN:OFFS", False, ("1", "1e999")))
    assert info.value.code == -222


# --------------------------------------------------------------------------- replies


def test_reply_lines_round_trip() -> None:
    assert parse_reply(encode_ok(tag=5)) == parse_reply(b"@5 OK\r\n")
    r = parse_reply(encode_value("SCAN:SIZE", 5000.0, 4000.0, tag=6))
    assert (r.tag, r.header, r.body) == (6, "SCAN:SIZE", "5000.0,4000.0")
    e = parse_reply(encode_error(-113, 'Undefined "header"', tag=7))
    assert e.header == "ERR"
    assert parse_error_body(e.body) == (-113, "Undefined 'header'")


def test_error_reply_becomes_instrument_error_with_its_code() -> None:
    with pytest.raises(InstrumentError) as info:
        check_header(
            parse_reply(b'@1 ERR -222,"Data out of range"\n'), "OK", command="SCAN:RATE 9e9"
        )
    assert info.value.code == -222
    assert "SCAN:RATE 9e9" in str(info.value)


def test_reply_for_another_command_is_out_of_sequence() -> None:
    with pytest.raises(OutOfSequenceError):
        check_header(parse_reply(b"@1 SCAN:SIZE 1.0,2.0\n"), "SCAN:OFFS")


def test_channels_and_events_round_trip() -> None:
    sample = ChannelSample(t_s=12.5, values={"temperature_c": 23.25, "humidity_pct": 41.0})
    back = decode_channels(parse_reply(encode_channels(sample, tag=1)).body)
    assert back.t_s == 12.5
    assert dict(back.values) == dict(sample.values)
    ev = Event(t_s=3.5, kind=EventKind.OFFSET_MOVE, x_nm=-10.0, y_nm=2.5)
    assert decode_event(parse_reply(encode_event(7, ev, tag=2)).body) == (7, ev)


@pytest.mark.parametrize(
    "body",
    ["", "temperature_c=1", "t=1,t=2", "t=1,Temp=2", "t=nan", "t=1,x"],
)
def test_malformed_channel_replies_raise_protocol_error(body: str) -> None:
    with pytest.raises(ProtocolError):
        decode_channels(body)


# --------------------------------------------------------------------------- frames


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_frame_block_round_trips_exactly(dtype: type) -> None:
    frame = _frame(dtype=dtype)
    data = encode_frame_reply(frame, tag=3)
    back, used = decode_frame_reply(data + b"tail", tag=3)
    assert used == len(data)
    assert back is not None
    assert back.heights_nm.dtype == dtype
    np.testing.assert_array_equal(back.heights_nm, frame.heights_nm)
    assert (back.index, back.t_start_s, back.t_end_s, back.direction, back.pixel_size_nm) == (
        frame.index,
        frame.t_start_s,
        frame.t_end_s,
        frame.direction,
        frame.pixel_size_nm,
    )


def test_no_frame_yet() -> None:
    assert decode_frame_reply(encode_no_frame(tag=1), tag=1) == (None, len(b"@1 #FRAME NONE\n"))


def test_corrupted_payload_byte_is_a_checksum_error() -> None:
    data = bytearray(encode_frame_reply(_frame(), tag=1))
    data[-5] ^= 0x10
    with pytest.raises(ChecksumError):
        decode_frame_reply(bytes(data), tag=1)


def test_corrupted_header_time_is_a_checksum_error() -> None:
    """Regression guard: the CRC covers the header, so a wrong t_start is never returned."""
    data = encode_frame_reply(_frame(index=4), tag=1).replace(b"t_start=1024.0", b"t_start=1025.0")
    with pytest.raises(ChecksumError):
        decode_frame_reply(data, tag=1)


def test_short_payload_is_a_protocol_error() -> None:
    data = encode_frame_reply(_frame(), tag=1)
    with pytest.raises(ProtocolError, match="payload"):
        decode_frame_reply(data[:-1], tag=1)


def test_frame_with_wrong_tag_is_out_of_sequence() -> None:
    with pytest.raises(OutOfSequenceError):
        decode_frame_reply(encode_frame_reply(_frame(), tag=1), tag=2)


# --------------------------------------------------------------------------- fuzzing


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_fuzz_reply_parsers_raise_only_protocol_errors(data: bytes) -> None:
    for parse in (
        lambda: parse_reply(data),
        lambda: decode_frame_reply(data, tag=None),
        lambda: decode_channels(data.decode("latin-1")),
        lambda: decode_event(data.decode("latin-1")),
        lambda: parse_error_body(data.decode("latin-1")),
    ):
        with contextlib.suppress(ProtocolError):
            parse()


_FRAME = _frame(rows=5, cols=4, index=3)
_ENCODED = encode_frame_reply(_FRAME, tag=42)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(
        st.tuples(st.integers(0, len(_ENCODED) - 1), st.integers(1, 255)), min_size=1, max_size=4
    ),
    st.integers(0, len(_ENCODED)),
)
def test_fuzz_corrupted_frame_reply_never_returns_a_wrong_frame(
    flips: list[tuple[int, int]], cut: int
) -> None:
    """Corrupt and truncate a valid block: the decoder either raises a typed error or
    returns exactly the original frame (never a different one)."""
    data = bytearray(_ENCODED)
    for pos, xor in flips:
        data[pos] ^= xor
    data = data[: max(cut, len(_ENCODED) // 2)]
    try:
        frame, _ = decode_frame_reply(bytes(data), tag=42)
    except ProtocolError:
        return  # any other exception fails the test
    assert frame is not None
    np.testing.assert_array_equal(frame.heights_nm, _FRAME.heights_nm)
    assert (frame.index, frame.t_start_s, frame.t_end_s, frame.pixel_size_nm) == (
        _FRAME.index,
        _FRAME.t_start_s,
        _FRAME.t_end_s,
        _FRAME.pixel_size_nm,
    )


def test_event_of_a_lab_kind_round_trips_and_a_malformed_kind_is_a_protocol_error() -> None:
    ev = Event(12.5, "door_open", 0.0, 0.0)
    index, back = decode_event(parse_reply(encode_event(3, ev)).body)
    assert (index, back) == (3, ev)
    assert not isinstance(back.kind, EventKind)
    with pytest.raises(ProtocolError, match="event kind 'Door Open'"):
        decode_event("4,1.0,Door Open,0,0")
