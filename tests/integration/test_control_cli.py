"""``afmdrift control``, run as a user runs it, against a daemon on loopback.

Exit status 0 when the daemon did it, 1 when it refused, 2 for an error (no
daemon answering, bad arguments, an unreadable token file). The daemon has
no instrument (a closed port): the control socket works regardless.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
from pathlib import Path

import pytest
import zmq.asyncio
from service_sim import closed_port, driver, run_afmdrift, running_service, service_config

from afmdrift.config import parse_config
from afmdrift.wire import ControlReply


async def _afmdrift(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """The command in a subprocess; the daemon's event loop goes on meanwhile."""
    return await asyncio.to_thread(run_afmdrift, *args, cwd=cwd, timeout=120)


@pytest.mark.asyncio
async def test_control_cli_exit_codes(tmp_path: Path, ctx: zmq.asyncio.Context) -> None:
    """0 for status, add-term and remove-term done; 1 for a term already there
    and one that does not parse (the reason on stderr; --json prints the
    reply); 2 for no daemon answering, a missing argument, no token file."""
    base = service_config(tmp_path / "run")
    cfg = parse_config(
        {
            "service": base.service.model_dump(),
            "registration": base.registration.model_dump(),
            "model": {"predictor": "physics", "physics": {"terms": ["trend", "warmup"]}},
        }
    )
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        ep = ["--endpoint", svc.control_endpoint]
        auth = [*ep, "--token-file", str(svc.control_token_path)]

        done = await _afmdrift("control", "status", *ep, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        assert "terms: trend, warmup;" in done.stdout
        assert len(done.stdout.splitlines()) == 1

        done = await _afmdrift("control", "add-term", "humidity", *auth, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        assert done.stdout.strip() == "add_term: ok; terms: trend, warmup, humidity"

        refused = await _afmdrift("control", "add-term", "humidity", *auth, cwd=tmp_path)
        assert refused.returncode == 1
        assert "'humidity' is already a term of the model" in refused.stderr
        assert refused.stdout == ""

        refused = await _afmdrift(
            "control", "add-term", "event:door:slow", "--json", *auth, cwd=tmp_path
        )
        assert refused.returncode == 1
        reply = ControlReply.model_validate(json.loads(refused.stdout))
        assert not reply.ok
        assert "unknown option 'slow'" in (reply.error or "")

        done = await _afmdrift("control", "remove-term", "humidity", "--json", *auth, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        reply = ControlReply.model_validate(json.loads(done.stdout))
        assert reply.status is not None
        assert reply.status.terms == ["trend", "warmup"]

        # the default token file (runs/latest/control.token under the cwd) is not there
        error = await _afmdrift("control", "pause", *ep, cwd=tmp_path)
        assert error.returncode == 2
        assert "cannot read token file" in error.stderr
        error = await _afmdrift("control", "add-term", *auth, cwd=tmp_path)
        assert error.returncode == 2
        assert "required: term" in error.stderr
        assert svc.controller.config.model.physics.terms == ["trend", "warmup"]

    nobody = f"tcp://127.0.0.1:{closed_port()}"
    error = await _afmdrift(
        "control", "status", "--endpoint", nobody, "--timeout-s", "0.5", cwd=tmp_path
    )
    assert error.returncode == 2
    assert f"no reply from {nobody}" in error.stderr
