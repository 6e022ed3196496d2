"""Harness for the drift service's tests: a small simulated AFM served over a real
transport (loopback TCP or a pseudo-terminal), and a running service.

Used by tests/unit/test_service_daemon.py, tests/integration/test_service_*.py and
tests/soak/, and :func:`run_afmdrift` by the tests that run the command line as a
user does. Only the tests import the simulator; the service never does.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import signal
import socket
import sqlite3
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import zmq.asyncio

from afmdrift.config import AfmdriftConfig, parse_config
from afmdrift.drivers._nanoscope import NanoScopeDriver
from afmdrift.drivers.nanonis import NanonisDriver
from afmdrift.drivers.sim import Scenario, SimPhysics, SimulatedAFM, parse_scenario
from afmdrift.drivers.sim._nanonis_server import CLOCK_SIGNAL, SCAN_CHANNEL, NanonisSimServer
from afmdrift.drivers.sim._server import SimulatorServer
from afmdrift.service import DriftService

REPO = Path(__file__).resolve().parent.parent

FloatArray = npt.NDArray[np.float64]


def run_afmdrift(*args: str, cwd: Path, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    """``afmdrift ARGS`` run as a user runs it (a subprocess in ``cwd``), its
    output captured as text."""
    return subprocess.run(
        [sys.executable, "-m", "afmdrift", *args],
        cwd=cwd, capture_output=True, text=True, timeout=timeout,
    )  # fmt: skip


def small_scenario(**options: Any) -> Scenario:
    """The scenario of :func:`scenario_data` (same options), validated."""
    return parse_scenario(scenario_data(**options), source="service-test")


def scenario_data(
    *,
    seed: int = 7,
    pixels: int = 128,
    frame_period_s: float = 32.0,
    line_rate_hz: float = 8.0,
    drift_nm_per_sqrt_s: float = 0.05,
    thermal: bool = True,
    warmup_nm: tuple[float, float] | None = None,
    warmup_tau_s: float = 2000.0,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A fast scenario as a TOML-like mapping.

    ``pixels``² frames of a textured gold sample with mild drift (random walk,
    thermal, and optionally a power-on settling ``warmup_nm``).

    4 nm per pixel; a frame's trace takes ``pixels / line_rate_hz`` s of
    instrument time and frames start every ``frame_period_s``.
    """
    data: dict[str, Any] = {
        "name": "service-test",
        "seed": seed,
        "duration_s": 30 * 86400.0,
        "scan": {
            "pixels": [pixels, pixels],
            "size_nm": [4.0 * pixels, 4.0 * pixels],
            "line_rate_hz": line_rate_hz,
            "frame_period_s": frame_period_s,
            "directions": "up",
        },
        "sample": {
            "kind": "gold_on_mica",
            "grid_nm": 2.0,
            "map_px": 1024,
            "roughness_nm": 0.3,
            "gold": {"density_per_um2": 80.0},
        },
        "physics": {
            "random_walk": {
                "enabled": True,
                "sigma_nm_per_sqrt_s": [drift_nm_per_sqrt_s, drift_nm_per_sqrt_s],
            },
            "thermal": {"enabled": thermal},
        },
    }
    if warmup_nm is not None:
        data["physics"]["warmup"] = {
            "enabled": True,
            "amplitude_nm": list(warmup_nm),
            "tau_s": warmup_tau_s,
        }
    for key, value in (extra or {}).items():
        data[key] = value
    return data


def humid_scenario(*, period_s: float = 600.0, beta_nm_per_pct: float = 6.0) -> dict[str, Any]:
    """Drift that follows the logged relative humidity (a cycle of 5 %RH).

    A model without the ``humidity`` term follows it late, through its
    residual; adding the term moves the prediction by several nm at once
    (what d(t) must not jump by)."""
    data = scenario_data(
        seed=5, frame_period_s=20.0, line_rate_hz=8.0, drift_nm_per_sqrt_s=0.02, thermal=False
    )
    data["physics"]["humidity"] = {
        "enabled": True,
        "mean_pct": 45.0,
        "amplitude_pct": 5.0,
        "period_s": period_s,
        "fluctuation_pct": 0.2,
        "beta_nm_per_pct": [beta_nm_per_pct, -0.7 * beta_nm_per_pct],
    }
    return data


def write_scenario(path: Path, data: dict[str, Any]) -> Path:
    """Write a scenario mapping as TOML (tables of scalars and lists only)."""

    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list | tuple):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    lines: list[str] = []

    def table(prefix: str, d: dict[str, Any]) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict)}
        if prefix:
            lines.append(f"[{prefix}]")
        lines.extend(f"{k} = {value(v)}" for k, v in scalars.items())
        for k, v in d.items():
            if isinstance(v, dict):
                table(f"{prefix}.{k}" if prefix else k, v)

    table("", data)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


class SimProcess:
    """``afmdrift sim serve`` in a subprocess on 127.0.0.1 (killable with SIGKILL)."""

    def __init__(
        self, scenario_file: Path, *, speed: float, port: int = 0, faults: float = 0.0
    ) -> None:
        self.scenario_file = scenario_file
        self.speed = speed
        self.port = port
        self.faults = faults
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> str:
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "afmdrift",
                "sim",
                "serve",
                "--port",
                str(self.port),
                "--scenario",
                str(self.scenario_file),
                "--speed",
                str(self.speed),
                "--faults",
                str(self.faults),
            ],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline().strip()
        if not line.isdigit():
            self.kill()
            raise RuntimeError(f"afmdrift sim serve did not print its port (got {line!r})")
        self.port = int(line)
        return f"socket://127.0.0.1:{self.port}"

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
        if self.proc is not None:
            self.proc.wait(timeout=30)
            if self.proc.stdout is not None:
                self.proc.stdout.close()


@contextlib.asynccontextmanager
async def sim_server(
    scenario: Scenario, *, speed: float, transport: str = "tcp", port: int = 0
) -> AsyncIterator[tuple[SimulatorServer, str]]:
    """A :class:`SimulatorServer` on loopback TCP or a pty, and its client URL."""
    sim = SimulatedAFM(scenario)
    server = SimulatorServer(sim, speed=speed)
    try:
        if transport == "pty":
            url = await server.start_pty()
        else:
            bound = await server.start_tcp(port, host="127.0.0.1")
            url = f"socket://127.0.0.1:{bound}"
        yield server, url
    finally:
        await server.stop()


def service_config(
    run_dir: Path,
    *,
    model: dict[str, Any] | None = None,
    registration: dict[str, Any] | None = None,
    **service: Any,
) -> AfmdriftConfig:
    """Configuration for tests: loopback with free ports, fast loops, small blocks
    (``model`` and ``registration`` replace those sections' test defaults)."""
    base: dict[str, Any] = {
        "pub_endpoint": "tcp://127.0.0.1:*",
        "control_endpoint": "tcp://127.0.0.1:*",
        "run_dir": str(run_dir),
        "frame_poll_interval_s": 0.05,
        "channel_poll_interval_s": 0.2,
        "event_poll_interval_s": 0.2,
        "clock_sync_interval_s": 0.1,
        "heartbeat_interval_s": 0.1,
        "reconnect_delay_s": 0.1,
        "max_offset_rate_nm_s": 1000.0,
        # A test of the live diagnosis turns it on; the others need no child process.
        "diagnose_every_frames": 0,
    }
    base.update(service)
    return parse_config(
        {
            "service": base,
            "registration": registration or {"block_size": 32, "extended_size": 64},
            "model": {"predictor": "constant_velocity"} if model is None else model,
        }
    )


def driver(url: str) -> NanoScopeDriver:
    """The production driver on ``url`` with short timeouts for tests."""
    return NanoScopeDriver(
        url, timeout_s=1.0, frame_timeout_s=5.0, reconnect_attempts=2, backoff_initial_s=0.05
    )


@contextlib.asynccontextmanager
async def running_service(
    config: AfmdriftConfig, instrument: Any, ctx: zmq.asyncio.Context
) -> AsyncIterator[DriftService]:
    """Run a :class:`DriftService` as a task; cancel it and wait for its cleanup on exit."""
    service = DriftService(config=config, instrument=instrument, ctx=ctx)
    task = asyncio.create_task(service.run())
    ready = asyncio.create_task(service.ready.wait())
    done, _ = await asyncio.wait({task, ready}, return_when=asyncio.FIRST_COMPLETED)
    if task in done:
        ready.cancel()
        await asyncio.gather(ready, return_exceptions=True)
        task.result()  # raises the startup error
    try:
        yield service
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


#: The model of the closed-loop runs on the Nanonis simulator: the project's
#: default registration, with the hysteresis of the offset moves (a play)
#: that ``afmdrift diagnose`` names on a closed-loop run of the default
#: scenario.
CLOSED_LOOP_TERMS = ["trend", "warmup", "thermal_lag", "creep", "hysteresis", "scan_direction"]


def closed_loop_config(
    run_dir: Path,
    actuator: str,
    *,
    terms: list[str] | None = CLOSED_LOOP_TERMS,
    **service: Any,
) -> AfmdriftConfig:
    """The closed-loop runs' configuration: the project's default registration,
    the model of ``terms`` (None: the project's default model), the service's
    loops fast, the loop's interval 0.1 s of wall time, every correction sent
    through ``actuator`` (``service`` overrides the service settings)."""
    settings: dict[str, Any] = {
        "closed_loop": True,
        "closed_loop_actuator": actuator,
        "closed_loop_interval_s": 0.1,
        "closed_loop_min_step_nm": 0.0,
        **service,
    }
    svc = service_config(run_dir, **settings).service
    data: dict[str, Any] = {"service": svc.model_dump(mode="json", exclude_defaults=True)}
    if terms is not None:
        data["model"] = {"physics": {"terms": list(terms)}}
    return parse_config(data)


@contextlib.asynccontextmanager
async def nanonis_closed_loop(
    sim: SimulatedAFM,
    run_dir: Path,
    ctx: zmq.asyncio.Context,
    *,
    speed: float,
    actuator: str = "velocity",
    terms: list[str] | None = CLOSED_LOOP_TERMS,
    **service: Any,
) -> AsyncIterator[tuple[DriftService, NanonisDriver, NanonisSimServer]]:
    """The daemon's closed loop on ``sim`` served over the Nanonis protocol on
    loopback TCP at ``speed``: the production driver (with a wait connection)
    and :func:`closed_loop_config` (``terms``, ``service``)."""
    async with NanonisSimServer(sim, speed=speed) as server:
        port = await server.start_tcp(0)
        driver = NanonisDriver(
            f"nanonis://127.0.0.1:{port}",
            wait_transport=f"nanonis://127.0.0.1:{port}",
            channel_index=SCAN_CHANNEL,
            channels={"temperature_c": "Temperature (C)", "humidity_pct": "Humidity (%)"},
            clock_signal=CLOCK_SIGNAL,
            wait_ms=100,
        )
        cfg = closed_loop_config(run_dir, actuator, terms=terms, **service)
        async with running_service(cfg, driver, ctx) as running:
            yield running, driver, server


@dataclasses.dataclass(frozen=True)
class Residual:
    """RMS and peak of ``|r(t)|`` over the samples, nm."""

    rms_nm: float
    peak_nm: float

    @classmethod
    def of(cls, r: FloatArray) -> Residual:
        """From residuals of shape (n, 2), nm."""
        norm = np.hypot(r[:, 0], r[:, 1])
        return cls(float(np.sqrt(np.mean(norm**2))), float(norm.max()))


def content_residual(physics: SimPhysics, t: FloatArray, *, t_ref_s: float) -> Residual:
    """Where image content sits, ``p − o``, on ``t`` relative to where it sat at ``t_ref_s``."""
    c = physics.drift_at(t) - physics.scan_offset_at(t)
    ref = physics.drift_at(t_ref_s) - physics.scan_offset_at(t_ref_s)
    return Residual.of(c - ref)


def committed_frames(run_dir: Path) -> int:
    """Frames a running daemon has committed to ``run_dir``'s store (read-only,
    beside its writes; 0 before the store and its schema exist)."""
    db_path = run_dir / "run.sqlite"
    if not db_path.is_file():
        return 0
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db_path}?mode=ro", uri=True)) as db:
            return int(db.execute("SELECT COUNT(*) FROM frames").fetchone()[0])
    except sqlite3.OperationalError:
        return 0


def closed_port() -> int:
    """A loopback TCP port nothing listens on (an instrument that is not there)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
