"""The simulator's command dispatch (controller side of the protocol), line by line."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from afmdrift.drivers._protocol import (
    COMMANDS,
    decode_frame_header,
    decode_frame_reply,
    parse_error_body,
    parse_reply,
)
from afmdrift.drivers.sim import Scenario, SimulatedAFM
from afmdrift.drivers.sim._server import (
    ERROR_QUEUE_SIZE,
    ServerFaults,
    SimulatorServer,
    VirtualClock,
)

SCENARIO = {
    "name": "dispatch",
    "scan": {"pixels": [16, 16], "size_nm": [400.0, 400.0], "line_rate_hz": 16.0},
    "sample": {"map_px": 256},
}


class FakeWall:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def wall() -> FakeWall:
    return FakeWall()


@pytest.fixture
def server(wall: FakeWall) -> SimulatorServer:
    sim = SimulatedAFM(Scenario.model_validate(SCENARIO), seed=1)
    clock = VirtualClock(speed=10.0, start_s=sim.now_s, wall=wall)
    return SimulatorServer(sim, clock=clock)


def _ask(server: SimulatorServer, line: bytes) -> tuple[str, str]:
    reply, _ = server.handle_line(line)
    r = parse_reply(reply.split(b"\n", 1)[0])
    return r.header, r.body


@pytest.mark.parametrize(
    ("line", "code"),
    [
        (b"FOO:BAR?\n", -113),
        (b"SCAN:START?\n", -113),  # no query form
        (b"SCAN:STAT 1\n", -113),  # no set form
        (b"SCAN:OFFS 1\n", -109),
        (b"SCAN:OFFS 1,2,3\n", -108),
        (b"SCAN:OFFS 1,x\n", -104),
        (b"SCAN:PIX 1.5,2\n", -104),
        (b"EVENT:LOG? -1\n", -104),
        (b"SCAN:RATE 1e999\n", -222),
        (b"SCAN:\x01RATE?\n", -101),
        (b",,,\n", -102),
        (b"FRAME:TIME?\n", -230),  # before the first frame
    ],
)
def test_invalid_commands_get_scpi_errors_and_are_queued(
    server: SimulatorServer, line: bytes, code: int
) -> None:
    server.sim.stop()
    header, body = _ask(server, line)
    assert header == "ERR"
    assert parse_error_body(body)[0] == code
    assert [c for c, _ in server.error_queue] == [code]
    assert _ask(server, b"SYST:ERR?\n")[1].startswith(f"{code},")
    assert _ask(server, b"SYST:ERR?\n") == ("SYST:ERR", '0,"No error"')


def test_out_of_range_value_from_the_simulator_is_minus_222(server: SimulatorServer) -> None:
    server.sim.stop()
    header, body = _ask(server, b"@4 SCAN:PIX 0,16\n")
    assert header == "ERR"
    code, message = parse_error_body(body)
    assert code == -222
    assert "SCAN:PIX 0,16" in message


def test_geometry_change_while_scanning_is_a_settings_conflict(server: SimulatorServer) -> None:
    server.sim.start()
    header, body = _ask(server, b"SCAN:RATE 8\n")
    assert (header, parse_error_body(body)[0]) == ("ERR", -221)


def test_error_queue_overflow_keeps_newest_as_minus_350(server: SimulatorServer) -> None:
    for _ in range(ERROR_QUEUE_SIZE + 3):
        server.handle_line(b"NOPE?\n")
    queue = server.error_queue
    assert len(queue) == ERROR_QUEUE_SIZE
    assert queue[-1][0] == -350
    assert all(c == -113 for c, _ in queue[:-1])
    assert _ask(server, b"*CLS\n") == ("OK", "")
    assert server.error_queue == []


def test_replies_echo_the_tag_on_every_line(server: SimulatorServer, wall: FakeWall) -> None:
    server.handle_line(b"SCAN:OFFS 3,4\n")
    reply, header = server.handle_line(b"@77 EVENT:LOG? 0\n")
    assert header == "EVENT:LOG"
    lines = reply.splitlines()
    assert len(lines) == 1 + len(server.sim.events)
    assert all(line.startswith(b"@77 ") for line in lines)


def test_frames_follow_the_virtual_clock(server: SimulatorServer, wall: FakeWall) -> None:
    assert _ask(server, b"FRAME:INDEX?\n") == ("FRAME:INDEX", "-1")
    assert server.handle_line(b"@1 FRAME:DATA?\n")[0] == b"@1 #FRAME NONE\n"
    wall.t = 0.5  # virtual 5 s: 16 lines at 16 Hz, so frames complete every ~1 s
    server.advance()
    index = int(_ask(server, b"FRAME:INDEX?\n")[1])
    assert index >= 1
    data, header = server.handle_line(b"@2 FRAME:DATA?\n")
    assert header == "FRAME:DATA"
    frame, used = decode_frame_reply(data, tag=2)
    assert used == len(data)
    truth = server.sim.latest_frame()
    assert frame is not None
    assert truth is not None
    np.testing.assert_array_equal(frame.heights_nm, truth.heights_nm)
    t = float(_ask(server, b"SYST:TIME?\n")[1])
    assert t == server.sim.now_s
    assert t <= server.clock.now_s()
    assert _ask(server, b"FRAME:TIME?\n")[1].startswith(f"{frame.index},")


def test_corrupt_fault_changes_bytes_but_not_line_ends() -> None:
    faults = ServerFaults(seed=5)
    faults.corrupt_next_reply(nbytes=8, where="header", match="SYST:TIME")
    reply = b"@1 SYST:TIME 12.5\n"
    assert faults.take("*IDN") is None
    fault = faults.take("SYST:TIME")
    assert fault is not None
    bad = faults.corrupt(reply, fault)
    assert bad != reply
    assert bad.count(b"\n") == 1
    assert bad.endswith(b"\n")
    assert faults.pending == 0
    assert faults.applied == [("corrupt", "SYST:TIME")]


def test_payload_corruption_leaves_the_header_intact(
    server: SimulatorServer, wall: FakeWall
) -> None:
    wall.t = 0.3
    server.advance()
    data, _ = server.handle_line(b"@3 FRAME:DATA?\n")
    faults = ServerFaults(seed=1)
    faults.corrupt_next_reply(nbytes=4, where="payload")
    fault = faults.take("FRAME:DATA")
    assert fault is not None
    bad = faults.corrupt(data, fault)
    head = bad.split(b"\n", 1)[0]
    assert head == data.split(b"\n", 1)[0]
    assert decode_frame_header(parse_reply(head)) is not None


def test_bad_fault_parameters_are_rejected() -> None:
    faults = ServerFaults()
    with pytest.raises(ValueError, match="count"):
        faults.drop_next_reply(count=0)
    with pytest.raises(ValueError, match="invalid fault"):
        faults.delay_next_reply(-1.0)


@pytest.mark.asyncio
async def test_overlong_line_over_tcp_is_input_buffer_overrun(server: SimulatorServer) -> None:
    """Regression guard: a line without a terminator must not grow the server's buffer
    without bound; it is dropped and answered with -363."""
    port = await server.start_tcp(0)
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(b"X" * 10_000 + b"\n@5 *IDN?\n")
        await writer.drain()
        first = await asyncio.wait_for(reader.readline(), 5)
        second = await asyncio.wait_for(reader.readline(), 5)
        writer.close()
        await writer.wait_closed()
    finally:
        await server.stop()
    assert first.startswith(b'ERR -363,"Input buffer overrun')
    assert second.startswith(b"@5 *IDN afmdrift,SimulatedAFM,")


@pytest.mark.parametrize(
    "header", sorted(h for h, spec in COMMANDS.items() if spec.query_args is not None)
)
def test_every_query_in_the_command_table_is_answered(server: SimulatorServer, header: str) -> None:
    """Regression guard: COMMANDS (used by docs and the driver) and the server's
    handlers stay in step; a documented query never gets -113."""
    args = ",".join("0" for _ in range(COMMANDS[header].query_args or 0))
    reply, _ = server.handle_line(f"@9 {header}? {args}\n".encode())
    first = parse_reply(reply.split(b"\n", 1)[0])
    assert first.tag == 9
    if first.header == "ERR":
        assert parse_error_body(first.body)[0] != -113


@pytest.mark.parametrize(
    ("line", "after"),
    [
        (b"*CLS\n", None),
        (b"SCAN:STOP\n", b"SCAN:STAT?\n"),
        (b"SCAN:START\n", b"SCAN:STAT?\n"),
        (b"SCAN:OFFS 1.5,2.5\n", b"SCAN:OFFS?\n"),
        (b"TIP:MOVE 10,20\n", None),
        (b"TIP:MAN 10,20,30,20\n", b"EVENT:COUNT?\n"),
    ],
)
def test_set_commands_answer_ok(server: SimulatorServer, line: bytes, after: bytes | None) -> None:
    assert _ask(server, line) == ("OK", "")
    if after is not None:
        header, _ = _ask(server, after)
        assert header == after.split(b"?")[0].decode()
