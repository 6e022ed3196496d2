"""The daemon's sockets without frames: status, control, validity, clean shutdown,
and the CURVE requirement for non-loopback binds."""

from __future__ import annotations

import asyncio
import io
from pathlib import Path

import pytest
import zmq
import zmq.asyncio
import zmq.auth
from service_sim import closed_port, driver, running_service, service_config

from afmdrift.client import ClientError, Subscriber, control
from afmdrift.client._watch import watch
from afmdrift.config import parse_config
from afmdrift.service import DriftService
from afmdrift.service._zmq import ServiceSocketError, load_curve_keys
from afmdrift.wire import OffsetMsg, StatusMsg


async def _next(sub: Subscriber, kind: type, *, timeout_s: float = 5.0):  # type: ignore[no-untyped-def]
    async with asyncio.timeout(timeout_s):
        while True:
            msg = await sub.recv()
            if isinstance(msg, kind):
                return msg


@pytest.mark.asyncio
async def test_unreachable_instrument_gives_invalid_offsets_and_instrument_error(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    """Regression guard: without an instrument the daemon keeps running and says so;
    it never publishes a 'valid' offset."""
    cfg = service_config(tmp_path / "run")
    instrument = driver(f"socket://127.0.0.1:{closed_port()}")
    async with running_service(cfg, instrument, ctx) as service:
        sub = Subscriber(service.pub_endpoint, ctx=ctx)
        try:
            status = await _next(sub, StatusMsg)
            while "instrument_error" not in status.flags:
                status = await _next(sub, StatusMsg)
            assert "no_model" in status.flags
            assert status.frames == 0
            offset = await _next(sub, OffsetMsg)
            assert not offset.valid
            assert sub.is_stale()
        finally:
            sub.close()


@pytest.mark.asyncio
async def test_control_socket_pause_resume_and_bad_request(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    cfg = service_config(tmp_path / "run")
    instrument = driver(f"socket://127.0.0.1:{closed_port()}")
    async with running_service(cfg, instrument, ctx) as service:
        token = service.control_token_path
        reply = await control(service.control_endpoint, "pause", token_file=token, ctx=ctx)
        assert reply.status is not None
        assert reply.status.state == "paused"
        assert "paused" in reply.status.flags
        reply = await control(service.control_endpoint, "resume", token_file=token, ctx=ctx)
        assert reply.status is not None
        assert reply.status.state != "paused"
        reply = await control(
            service.control_endpoint, "reset_reference", token_file=token, ctx=ctx
        )
        assert reply.ok
        # reload_model without a config file names the missing item
        with pytest.raises(ClientError, match="config_path"):
            await control(service.control_endpoint, "reload_model", token_file=token, ctx=ctx)
        req = ctx.socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        try:
            req.connect(service.control_endpoint)
            await req.send(b'{"v": 1, "cmd": "self_destruct"}')
            answer = await asyncio.wait_for(req.recv(), 5.0)
        finally:
            req.close()
        assert b'"ok":false' in answer
        assert b"control request" in answer


@pytest.mark.asyncio
async def test_reload_model_reads_the_named_file(tmp_path: Path, ctx: zmq.asyncio.Context) -> None:
    cfg = service_config(tmp_path / "run", reload_config_dir=str(tmp_path))
    new = tmp_path / "new.toml"
    new.write_text('[model]\npredictor = "last_value"\n', encoding="utf-8")
    bad = tmp_path / "bad.toml"
    bad.write_text('[model]\npredictor = "crystal_ball"\n', encoding="utf-8")
    instrument = driver(f"socket://127.0.0.1:{closed_port()}")
    async with running_service(cfg, instrument, ctx) as service:
        token = service.control_token_path
        await control(
            service.control_endpoint,
            "reload_model",
            config_path=str(new),
            token_file=token,
            ctx=ctx,
        )
        assert service.pipeline.predictor.name == "last_value"
        with pytest.raises(ClientError, match="crystal_ball"):
            await control(
                service.control_endpoint,
                "reload_model",
                config_path=str(bad),
                token_file=token,
                ctx=ctx,
            )
        assert service.pipeline.predictor.name == "last_value"


def test_off_loopback_bind_without_key_files_refuses_to_start(tmp_path: Path) -> None:
    """The daemon refuses to start when CURVE key files are configured but unusable."""
    cfg = parse_config(
        {
            "service": {
                "pub_endpoint": "tcp://*:5999",
                "curve_secret_key_file": str(tmp_path / "missing.key_secret"),
                "curve_authorized_clients_dir": str(tmp_path),
            }
        }
    )
    with pytest.raises(ServiceSocketError, match="curve_secret_key_file"):
        load_curve_keys(cfg.service)

    async def start() -> None:
        service = DriftService(config=cfg, instrument=driver("socket://127.0.0.1:1"))
        await service.run()

    with pytest.raises(ServiceSocketError, match="curve_secret_key_file"):
        asyncio.run(start())


def test_curve_keys_load_from_certificates(tmp_path: Path) -> None:
    keys = tmp_path / "keys"
    keys.mkdir()
    clients = tmp_path / "clients"
    clients.mkdir()
    _, secret_file = zmq.auth.create_certificates(str(keys), "server")
    zmq.auth.create_certificates(str(clients), "client")
    cfg = parse_config(
        {
            "service": {
                "control_endpoint": "tcp://*:5998",
                "curve_secret_key_file": secret_file,
                "curve_authorized_clients_dir": str(clients),
            }
        }
    )
    loaded = load_curve_keys(cfg.service)
    assert loaded is not None
    assert len(loaded.public) == 40
    public_only = parse_config(
        {
            "service": {
                "control_endpoint": "tcp://*:5998",
                "curve_secret_key_file": str(keys / "server.key"),
                "curve_authorized_clients_dir": str(clients),
            }
        }
    )
    with pytest.raises(ServiceSocketError, match="no secret key"):
        load_curve_keys(public_only.service)
    assert load_curve_keys(service_config(tmp_path).service) is None


@pytest.mark.asyncio
async def test_watch_prints_offsets_and_state(tmp_path: Path, ctx: zmq.asyncio.Context) -> None:
    cfg = service_config(tmp_path / "run")
    instrument = driver(f"socket://127.0.0.1:{closed_port()}")
    out = io.StringIO()
    async with running_service(cfg, instrument, ctx) as service:
        await watch(service.pub_endpoint, interval_s=0.2, duration_s=1.0, out=out, ctx=ctx)
    lines = out.getvalue().splitlines()
    assert len(lines) >= 3
    assert any("INVALID" in line and "instrument_error" in line for line in lines)
