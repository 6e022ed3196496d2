"""``afmdrift sim serve`` as a user runs it: a subprocess, a real pty or TCP port, a signal."""

from __future__ import annotations

import select
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from afmdrift.config import DriverConfig
from afmdrift.drivers import NanoScopeDriver, instrument_from_config

SCENARIO_TOML = """
name = "cli-test"
[scan]
pixels = [32, 32]
size_nm = [500.0, 500.0]
line_rate_hz = 64.0
[sample]
map_px = 256
"""


@pytest.fixture
def scenario_file(tmp_path: Path) -> Path:
    path = tmp_path / "small.toml"
    path.write_text(SCENARIO_TOML, encoding="utf-8")
    return path


def _serve(scenario: Path, *where: str) -> subprocess.Popen[str]:
    args = ["--scenario", str(scenario), "--speed", "20", "--seed", "3"]
    return subprocess.Popen(
        [sys.executable, "-m", "afmdrift", "sim", "serve", *where, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.fixture
def serve_tcp(scenario_file: Path) -> Iterator[tuple[subprocess.Popen[str], str]]:
    proc = _serve(scenario_file, "--port", "0")
    yield from _started(proc, lambda line: f"socket://127.0.0.1:{int(line)}")


@pytest.fixture
def serve_pty(scenario_file: Path) -> Iterator[tuple[subprocess.Popen[str], str]]:
    proc = _serve(scenario_file, "--pty")
    yield from _started(proc, lambda line: line)


def _started(proc: subprocess.Popen[str], to_url):  # type: ignore[no-untyped-def]
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().strip()
        assert line, f"server printed nothing; stderr: {proc.stderr.read() if proc.stderr else ''}"
        yield proc, to_url(line)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=30)


async def _session(url: str) -> None:
    driver = instrument_from_config(
        DriverConfig(transport=url, timeout_s=5.0, backoff_initial_s=0.05)
    )
    assert isinstance(driver, NanoScopeDriver)
    async with driver:
        info = await driver.identify()
        assert info.serial == "sim-cli-test-3"
        assert await driver.pixels() == (32, 32)
        await driver.set_offset(1.0, 2.0)
        assert await driver.get_offset() == (1.0, 2.0)


@pytest.mark.slow
@pytest.mark.asyncio
async def test_serve_tcp_then_sigterm_exits_cleanly(
    serve_tcp: tuple[subprocess.Popen[str], str],
) -> None:
    proc, url = serve_tcp
    await _session(url)
    await _session(url)  # a second client after the first has gone
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) == 0


@pytest.mark.slow
def test_serve_says_what_it_serves_beside_the_port_line(
    serve_tcp: tuple[subprocess.Popen[str], str],
) -> None:
    """Regression: ``sim serve`` printed only a port number. The port stays the
    first line on stdout (scripts read it); the description goes to stderr."""
    proc, url = serve_tcp
    assert proc.stderr is not None
    ready, _, _ = select.select([proc.stderr], [], [], 30)
    assert ready, "sim serve said nothing on stderr"
    said = proc.stderr.readline()
    host_port = url.removeprefix("socket://")
    assert "scenario 'cli-test' (seed 3)" in said
    assert f"over the line protocol on {host_port}" in said
    assert "at 20x real time" in said
    assert f"--instrument {url}" in said


@pytest.mark.slow
@pytest.mark.asyncio
async def test_serve_pty_then_sigint_exits_cleanly(
    serve_pty: tuple[subprocess.Popen[str], str],
) -> None:
    proc, path = serve_pty
    assert path.startswith("/dev/")
    await _session(path)
    await _session(path)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=30) == 0


@pytest.mark.slow
def test_serve_on_a_busy_port_is_a_clear_error(scenario_file: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        proc = _serve(scenario_file, "--port", str(port))
        _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert f"--port {port}: cannot listen on 127.0.0.1:{port}" in err
    assert "Traceback" not in err
