"""Hostile and faulty input on the control socket: every message gets a clear answer,
no message ends a task of the daemon, and only the token holder changes its state.

Each regression test names the case it guards against (issue "A daemon that
cannot be knocked over"). The daemon runs without an instrument (a closed
port): the control socket and the offset stream must work regardless.
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zmq
import zmq.asyncio
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from service_sim import closed_port, driver, running_service, service_config

from afmdrift.client import ClientError, Subscriber, control
from afmdrift.service import DriftService
from afmdrift.wire import OffsetMsg, decode_control_reply


async def _raw(ctx: zmq.asyncio.Context, endpoint: str, frames: list[bytes], kind: int) -> bytes:
    """Send ``frames`` from a socket of ``kind``; return the reply payload (last frame)."""
    sock = ctx.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        sock.connect(endpoint)
        await sock.send_multipart(frames)
        async with asyncio.timeout(5.0):
            reply = await sock.recv_multipart()
    finally:
        sock.close()
    return reply[-1]


async def _alive(service: DriftService, ctx: zmq.asyncio.Context) -> None:
    """The daemon still answers and still publishes offsets."""
    reply = await control(service.control_endpoint, "status", ctx=ctx)
    assert reply.ok
    sub = Subscriber(service.pub_endpoint, topics=("offset",), ctx=ctx)
    try:
        async with asyncio.timeout(5.0):
            async for msg in sub:
                if isinstance(msg, OffsetMsg):
                    break
    finally:
        sub.close()


@pytest.mark.asyncio
async def test_malformed_messages_get_error_replies_and_kill_nothing(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    """Regression: deeply nested JSON (RecursionError), an integer of 5000
    digits (ValueError), a two-part REQ message and a DEALER peer without the
    empty delimiter (ZMQError on reply) each ended the whole daemon."""
    cfg = service_config(tmp_path / "run")
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        ep = svc.control_endpoint
        deep = b"[" * 30_000 + b"]" * 30_000  # 60 kB: under the size limit
        answer = decode_control_reply(await _raw(ctx, ep, [deep], zmq.REQ))
        assert not answer.ok
        assert "nested deeper" in (answer.error or "")
        digits = b'{"v": 1, "cmd": "status", "n": ' + b"9" * 5000 + b"}"
        answer = decode_control_reply(await _raw(ctx, ep, [digits], zmq.REQ))
        assert not answer.ok
        assert "not usable JSON" in (answer.error or "")
        two = [b'{"v": 1, "cmd": "status"}', b"extra"]
        answer = decode_control_reply(await _raw(ctx, ep, two, zmq.REQ))
        assert "expected one frame, got 2" in (answer.error or "")
        dealer = decode_control_reply(
            await _raw(ctx, ep, [b'{"v": 1, "cmd": "status"}'], zmq.DEALER)
        )
        assert dealer.ok
        assert dealer.status is not None
        await _alive(svc, ctx)


@pytest.mark.asyncio
async def test_oversized_request_is_dropped_before_it_takes_memory(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    """Regression: a 100 MB request grew the daemon by 357 MB. Requests over
    control_max_request_bytes are dropped by ZeroMQ (the peer is disconnected)."""
    cfg = service_config(tmp_path / "run", control_max_request_bytes=4096)
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        try:
            sock.connect(svc.control_endpoint)
            await sock.send(b"x" * (1 << 20))
            assert await sock.poll(500) == 0  # no reply: dropped unread
        finally:
            sock.close()
        await _alive(svc, ctx)


@pytest.mark.asyncio
async def test_state_changing_commands_need_the_token(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    """Regression: any local user could pause the daemon or swap its model."""
    cfg = service_config(tmp_path / "run")
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        token_file = svc.control_token_path
        assert token_file == tmp_path / "run" / "control.token"
        assert token_file.stat().st_mode & 0o777 == 0o600
        ep = svc.control_endpoint
        for cmd in ("pause", "resume", "reset_reference", "reload_model"):
            with pytest.raises(ClientError, match="no token"):
                await control(ep, cmd, ctx=ctx)
            with pytest.raises(ClientError, match="wrong token"):
                await control(ep, cmd, token="guess", ctx=ctx)
        assert (await control(ep, "status", ctx=ctx)).ok  # reading needs no token
        assert not svc.publishing.paused
        reply = await control(ep, "pause", token_file=token_file, ctx=ctx)
        assert reply.status is not None
        assert reply.status.state == "paused"
    assert not token_file.exists()  # removed when the daemon stops


@pytest.mark.asyncio
async def test_reload_model_reads_only_regular_files_in_allowed_directories(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    """Regression: reload_model read any file (values echoed back in errors),
    blocked the event loop on a FIFO for 22 s and grew to 3 GB on /dev/zero."""
    allowed = tmp_path / "configs"
    allowed.mkdir()
    fifo = allowed / "fifo.toml"
    os.mkfifo(fifo)
    big = allowed / "big.toml"
    big.write_bytes(b"#" * (2 << 20))
    latin = allowed / "latin.toml"
    latin.write_bytes(b'[model]\npredictor = "caf\xe9"\n')
    cfg = service_config(tmp_path / "run", reload_config_dir=str(allowed))
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        tok = svc.control_token_path

        async def reload(path: str) -> str:
            with pytest.raises(ClientError) as err:
                await control(
                    svc.control_endpoint, "reload_model", config_path=path, token_file=tok, ctx=ctx
                )
            return str(err.value)

        assert "outside the directories" in await reload("/dev/zero")
        assert "outside the directories" in await reload("/etc/passwd")
        assert "outside the directories" in await reload(str(allowed / ".." / "x.toml"))
        assert "not a regular file" in await reload(str(fifo))
        assert "limit is" in await reload(str(big))
        assert "not UTF-8" in await reload(str(latin))
        await _alive(svc, ctx)


@pytest.mark.asyncio
async def test_reload_model_with_a_path_that_is_no_file_name(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    """Regression: a config_path with a lone surrogate (not encodable as a file
    name) raised UnicodeEncodeError and ended the daemon; it is refused when the
    request is decoded, in one line."""
    cfg = service_config(tmp_path / "run", reload_config_dir=str(tmp_path))
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        token = svc.control_token_path.read_text(encoding="ascii")
        request = json.dumps(
            {"v": 1, "cmd": "reload_model", "config_path": "\udcff.toml", "token": token}
        ).encode()
        answer = decode_control_reply(await _raw(ctx, svc.control_endpoint, [request], zmq.REQ))
        assert not answer.ok
        assert answer.error == (
            "control request: config_path: Input should be a valid string, "
            "unable to parse raw data as a unicode string"
        )
        await _alive(svc, ctx)


@pytest.mark.asyncio
@pytest.mark.parametrize(
    ("body", "expect"),
    [
        ("raise RuntimeError('broken plugin')", "RuntimeError: broken plugin"),
        ("import sys\nsys.exit(3)", "SystemExit: 3"),
    ],
    ids=["raises", "sys_exit"],
)
async def test_reload_model_with_a_plugin_that_fails_at_import(
    tmp_path: Path,
    ctx: zmq.asyncio.Context,
    monkeypatch: pytest.MonkeyPatch,
    body: str,
    expect: str,
) -> None:
    """Regression: a plugin raising at import ended the daemon (exit 1, or exit 3
    for sys.exit(3)); it is a configuration error now."""
    name = f"afmdrift_test_plugin_{abs(hash(body))}"
    (tmp_path / f"{name}.py").write_text(body + "\n", encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    new = tmp_path / "plugin.toml"
    new.write_text(
        f'[model]\npredictor = "physics"\n[model.physics]\nplugins = ["{name}:Term"]\n',
        encoding="utf-8",
    )
    cfg = service_config(tmp_path / "run", reload_config_dir=str(tmp_path))
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        with pytest.raises(ClientError, match=expect):
            await control(
                svc.control_endpoint,
                "reload_model",
                config_path=str(new),
                token_file=svc.control_token_path,
                ctx=ctx,
            )
        await _alive(svc, ctx)
    sys.modules.pop(name, None)


@pytest.mark.asyncio
async def test_model_command_and_status_sequence_numbers(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    """The ``model`` command answers without waiting for a frame; control replies
    take no numbers from the status topic (regression: they made false gaps)."""
    cfg = service_config(tmp_path / "run")
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        reply = await control(svc.control_endpoint, "model", ctx=ctx)
        assert reply.ok
        assert reply.model is None  # no model before the first frame
        sub = Subscriber(svc.pub_endpoint, topics=("status",), ctx=ctx)
        try:
            seqs: list[int] = []
            async with asyncio.timeout(10.0):
                async for msg in sub:
                    seqs.append(msg.seq)
                    assert msg.run_id == svc.publishing.run_id
                    for _ in range(3):
                        await control(svc.control_endpoint, "status", ctx=ctx)
                    if len(seqs) == 4:
                        break
        finally:
            sub.close()
        assert seqs == list(range(seqs[0], seqs[0] + 4))


# ---------------------------------------------------------------------- fuzzing


class _DaemonThread:
    """A daemon in its own thread and event loop, for synchronous Hypothesis tests."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        self.endpoint = ""
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, daemon=True)

    def __enter__(self) -> _DaemonThread:
        self._thread.start()
        assert self._ready.wait(60.0), "daemon did not start"
        if self._error is not None:
            raise self._error
        return self

    def __exit__(self, *exc: object) -> None:
        assert self._loop is not None
        assert self._stop is not None
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(30.0)
        if self._error is not None:
            raise self._error

    def _main(self) -> None:
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        ctx = zmq.asyncio.Context()
        try:
            cfg = service_config(self.run_dir)
            inst = driver(f"socket://127.0.0.1:{closed_port()}")
            async with running_service(cfg, inst, ctx) as svc:
                self.endpoint = svc.control_endpoint
                self._ready.set()
                await self._stop.wait()
        except BaseException as err:
            self._error = err
            self._ready.set()
        finally:
            ctx.term()


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[_DaemonThread]:
    with _DaemonThread(tmp_path_factory.mktemp("fuzz") / "run") as d:
        yield d


_json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=40),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=20,
)
_requests = st.one_of(
    st.binary(max_size=2048),
    _json_values.map(lambda v: json.dumps(v).encode()),
    st.fixed_dictionaries(
        {"v": st.sampled_from([1, 2, "1", None]), "cmd": st.text(max_size=20) | _json_values},
        optional={"config_path": _json_values, "token": _json_values},
    ).map(lambda d: json.dumps(d).encode()),
)


@settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(frames=st.lists(_requests, min_size=1, max_size=3), dealer=st.booleans())
def test_fuzz_control_socket_always_answers(
    daemon: _DaemonThread, frames: list[bytes], dealer: bool
) -> None:
    """Any message, from a REQ or a DEALER peer, gets one reply that decodes."""
    zctx = zmq.Context.instance()
    sock = zctx.socket(zmq.DEALER if dealer else zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, 5000)
    try:
        sock.connect(daemon.endpoint)
        sock.send_multipart(frames)
        reply = decode_control_reply(sock.recv_multipart()[-1])
    finally:
        sock.close()
    # A DEALER peer's leading empty frame is taken as the REQ delimiter.
    body = frames[1:] if dealer and frames[0] == b"" else frames
    if len(body) != 1:
        assert not reply.ok
    if reply.ok:  # only the read-only commands can succeed without the token
        assert json.loads(body[0])["cmd"] in ("status", "model")
