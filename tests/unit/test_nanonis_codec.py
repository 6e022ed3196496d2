"""The Nanonis TCP codec: tables of request and reply bytes, malformed replies, fuzzing."""

from __future__ import annotations

import contextlib
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmdrift.drivers import ProtocolError
from afmdrift.drivers.nanonis import COMMANDS, NanonisError
from afmdrift.drivers.nanonis._codec import (
    HEADER_SIZE,
    decode_body,
    decode_header,
    decode_reply,
    encode_body,
    encode_error_block,
    encode_header,
    encode_reply,
    encode_request,
)


def _name(name: str) -> bytes:
    return name.encode().ljust(32, b"\0")


def _ok() -> bytes:
    return struct.pack(">Ii", 0, 0)


# (command, arguments, expected request bytes) — layouts of the Nanonis TCP protocol document.
REQUESTS = [
    ("Scan.StatusGet", (), _name("Scan.StatusGet") + struct.pack(">IHH", 0, 1, 0)),
    (
        "Scan.WaitEndOfScan",
        (-1,),
        _name("Scan.WaitEndOfScan") + struct.pack(">IHH", 4, 1, 0) + struct.pack(">i", -1),
    ),
    (
        "Scan.FrameSet",
        (1e-7, -2e-7, 5e-7, 4e-7, 0.0),
        _name("Scan.FrameSet")
        + struct.pack(">IHH", 20, 1, 0)
        + struct.pack(">5f", 1e-7, -2e-7, 5e-7, 4e-7, 0.0),
    ),
    (
        "FolMe.XYPosSet",
        (1e-7, 2e-7, 1),
        _name("FolMe.XYPosSet")
        + struct.pack(">IHH", 20, 1, 0)
        + struct.pack(">ddI", 1e-7, 2e-7, 1),
    ),
    (
        "Signals.ValsGet",
        (np.array([0, 30]), 1),
        _name("Signals.ValsGet")
        + struct.pack(">IHH", 16, 1, 0)
        + struct.pack(">iiiI", 2, 0, 30, 1),
    ),
    (
        "Piezo.DriftCompSet",
        (2, 0.0, 0.0, 0.0, 10.0),
        _name("Piezo.DriftCompSet")
        + struct.pack(">IHH", 20, 1, 0)
        + struct.pack(">Iffff", 2, 0.0, 0.0, 0.0, 10.0),
    ),
]


@pytest.mark.parametrize(("name", "args", "expected"), REQUESTS, ids=[r[0] for r in REQUESTS])
def test_requests_encode_to_the_documented_bytes(name: str, args: tuple, expected: bytes) -> None:
    assert encode_request(name, *args) == expected
    header = decode_header(expected[:HEADER_SIZE])
    assert (header.name, header.body_size, header.response) == (name, len(expected) - 40, True)
    values, end = decode_body(COMMANDS[name].args, expected[HEADER_SIZE:])
    assert end == len(expected) - HEADER_SIZE
    for got, want in zip(values, args, strict=True):
        np.testing.assert_allclose(
            np.asarray(got, dtype=float), np.asarray(want, dtype=float), rtol=1e-6
        )


# (command, reply body, decoded values)
REPLIES = [
    ("Scan.StatusGet", struct.pack(">I", 1) + _ok(), (1,)),
    ("Scan.WaitEndOfScan", struct.pack(">Ii", 0, 3) + b"a/b" + _ok(), (0, "a/b")),
    (
        "Scan.BufferGet",
        struct.pack(">iiiii", 2, 14, 0, 256, 128) + _ok(),
        ([14, 0], 256, 128),
    ),
    (
        "Signals.NamesGet",
        struct.pack(">ii", 4 + 1 + 4 + 3, 2)
        + struct.pack(">i", 1)
        + b"X"
        + struct.pack(">i", 3)
        + b"Z m"
        + _ok(),
        (["X", "Z m"],),
    ),
    (
        "Scan.FrameDataGrab",
        struct.pack(">i", 5)
        + b"Z (m)"
        + struct.pack(">ii", 2, 3)
        + struct.pack(">6f", *range(6))
        + struct.pack(">I", 0)
        + _ok(),
        ("Z (m)", [[0, 1, 2], [3, 4, 5]], 0),
    ),
    ("FolMe.XYPosGet", struct.pack(">dd", 1.5e-7, -2.5e-7) + _ok(), (1.5e-7, -2.5e-7)),
]


@pytest.mark.parametrize(("name", "body", "expected"), REPLIES, ids=[r[0] for r in REPLIES])
def test_replies_decode_to_their_values(name: str, body: bytes, expected: tuple) -> None:
    header = decode_header(encode_header(name, len(body)))
    values = decode_reply(name, header, body)
    assert len(values) == len(expected)
    for got, want in zip(values, expected, strict=True):
        if isinstance(want, str) or (isinstance(want, list) and want and isinstance(want[0], str)):
            assert got == want
        else:
            np.testing.assert_allclose(np.asarray(got, dtype=float), np.asarray(want, dtype=float))
    # and the server side encodes the same bytes
    assert encode_reply(name, *values)[HEADER_SIZE:] == body


def test_a_frame_decodes_as_big_endian_float32_in_one_array() -> None:
    data = np.arange(12, dtype=np.float64).reshape(3, 4) * 1e-9
    reply = encode_reply("Scan.FrameDataGrab", "Z (m)", data, 1)
    header = decode_header(reply[:HEADER_SIZE])
    name, grid, up = decode_reply("Scan.FrameDataGrab", header, reply[HEADER_SIZE:])
    assert (name, up) == ("Z (m)", 1)
    assert grid.dtype == np.float32
    assert grid.dtype.isnative
    assert grid.shape == (3, 4)
    np.testing.assert_array_equal(grid, data.astype(np.float32))


def test_an_error_status_raises_a_typed_error_with_the_controller_text() -> None:
    body = struct.pack(">I", 0) + encode_error_block(7, "Scan is not running")
    header = decode_header(encode_header("Scan.StatusGet", len(body)))
    with pytest.raises(NanonisError, match="Scan is not running") as info:
        decode_reply("Scan.StatusGet", header, body)
    assert (info.value.code, info.value.command) == (7, "Scan.StatusGet")


def test_an_error_block_alone_raises_the_controller_error() -> None:
    reply = encode_reply("Scan.FrameGet", error=(1, "Unknown command"), types=())
    header = decode_header(reply[:HEADER_SIZE])
    with pytest.raises(NanonisError, match="Unknown command"):
        decode_reply("Scan.FrameGet", header, reply[HEADER_SIZE:])


MALFORMED = [
    ("truncated scalar", "Scan.StatusGet", b"\0\0"),
    ("no error block", "Scan.StatusGet", struct.pack(">I", 1)),
    ("bytes after the error block", "Scan.StatusGet", struct.pack(">I", 1) + _ok() + b"x"),
    ("negative count", "Scan.BufferGet", struct.pack(">i", -1) + _ok()),
    ("count beyond the body", "Signals.ValsGet", struct.pack(">i", 1 << 30) + _ok()),
    (
        "frame larger than the body",
        "Scan.FrameDataGrab",
        struct.pack(">i", 0) + struct.pack(">ii", 1 << 20, 1 << 20) + _ok(),
    ),
    ("string longer than the body", "Scan.WaitEndOfScan", struct.pack(">Ii", 0, 999) + _ok()),
    ("string array size mismatch", "Signals.NamesGet", struct.pack(">iii", 9, 1, 1) + b"X" + _ok()),
]


@pytest.mark.parametrize(("case", "name", "body"), MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_replies_are_protocol_errors(case: str, name: str, body: bytes) -> None:
    header = decode_header(encode_header(name, len(body)))
    with pytest.raises(ProtocolError):
        decode_reply(name, header, body)


@pytest.mark.parametrize(
    ("header", "message"),
    [
        (b"\0" * 40, "malformed command name"),
        (b"Scan.StatusGet".ljust(32, b"\0") + struct.pack(">IHH", 0xFFFFFFFF, 1, 0), "exceeds"),
        (b"short", "40 bytes"),
        (b"Scan\nGet".ljust(32, b"\0") + struct.pack(">IHH", 0, 1, 0), "malformed"),
    ],
)
def test_malformed_or_oversize_headers_are_refused(header: bytes, message: str) -> None:
    with pytest.raises(ProtocolError, match=message):
        decode_header(header)


def test_a_reply_naming_another_command_is_refused() -> None:
    reply = encode_reply("Scan.StatusGet", 1)
    header = decode_header(reply[:HEADER_SIZE])
    with pytest.raises(ProtocolError, match=r"names 'Scan\.StatusGet'"):
        decode_reply("Scan.FrameGet", header, reply[HEADER_SIZE:])


@settings(max_examples=300, deadline=None)
@given(name=st.sampled_from(sorted(COMMANDS)), body=st.binary(max_size=200))
def test_fuzzed_reply_bodies_never_crash(name: str, body: bytes) -> None:
    header = decode_header(encode_header(name, len(body)))
    with contextlib.suppress(ProtocolError, NanonisError):
        decode_reply(name, header, body)


@settings(max_examples=100, deadline=None)
@given(
    rows=st.integers(0, 6),
    cols=st.integers(1, 6),
    names=st.lists(st.text(max_size=12), max_size=5),
    values=st.lists(st.floats(width=32, allow_nan=False), max_size=8),
)
def test_arrays_and_strings_round_trip(
    rows: int, cols: int, names: list[str], values: list[float]
) -> None:
    grid = np.arange(rows * cols, dtype=np.float32).reshape(rows, cols)
    types = ("2f", "[str]", "[f]", "str")
    body = encode_body(types, (grid, names, values, "end"))
    out, end = decode_body(types, body)
    assert end == len(body)
    np.testing.assert_array_equal(out[0], grid)
    assert out[1] == names
    np.testing.assert_array_equal(out[2], np.asarray(values, dtype=np.float32))
    assert out[3] == "end"
