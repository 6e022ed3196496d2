"""The dashboard page in headless Chromium, against the simulator and the daemon over
loopback, and on a finished replay.

Set ``AFMDRIFT_DASHBOARD_SCREENSHOTS=DIR`` to also write the screenshots to DIR
(``AFMDRIFT_DASHBOARD_SCREENSHOTS=docs pytest tests/integration/test_dashboard.py``
regenerates ``docs/dashboard-live.png`` and ``docs/dashboard-replay.png``).
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from afmdrift.cli import main
from afmdrift.config import parse_config
from afmdrift.dashboard import Dashboard, load_session
from afmdrift.dashboard._chromium import HeadlessChromium, find_chromium
from afmdrift.service import replay_session

from service_sim import REPO, scenario_data, write_scenario  # isort: skip

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

needs_chromium = pytest.mark.skipif(
    find_chromium() is None,
    reason="chromium is not installed (Debian: apt-get install chromium; .ci/run installs it)",
)

PLOTS = ("plot-drift", "plot-offset", "plot-error", "plot-frame", "plot-channels")

#: Points drawn in each plot and whether Plotly rendered its SVG.
PLOT_CHECK = """(() => {
  const out = {};
  for (const id of PLOTS) {
    const gd = document.getElementById(id);
    let n = 0;
    for (const tr of (gd.data || [])) {
      const a = tr.z || tr.x || [];
      n += a.filter((v) => v !== null).length;
    }
    out[id] = { points: n, svg: gd.querySelectorAll(".main-svg").length };
  }
  return out;
})()""".replace("PLOTS", json.dumps(list(PLOTS)))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _save_screenshot(src: Path, name: str) -> None:
    out = os.environ.get("AFMDRIFT_DASHBOARD_SCREENSHOTS")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, Path(out) / name)


class _Process:
    """A command-line process of this checkout on loopback, killed with SIGKILL."""

    def __init__(self, args: list[str], log: Path) -> None:
        self.args = args
        self.log = log
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        with self.log.open("ab") as fh:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "afmdrift", *self.args],
                cwd=REPO,
                stdout=fh,
                stderr=subprocess.STDOUT,
            )

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
        if self.proc is not None:
            self.proc.wait(timeout=30)
        self.proc = None


def _daemon_config(path: Path, run_dir: Path, pub: str, control: str) -> Path:
    path.write_text(
        f"""[service]
pub_endpoint = "{pub}"
control_endpoint = "{control}"
run_dir = "{run_dir}"
archive_frames = true
offset_rate_hz = 200.0
frame_poll_interval_s = 0.05
channel_poll_interval_s = 0.2
event_poll_interval_s = 0.2
clock_sync_interval_s = 0.1
heartbeat_interval_s = 0.2
reconnect_delay_s = 0.1
max_offset_rate_nm_s = 1000.0

[registration]
block_size = 32
extended_size = 64

[model]
predictor = "constant_velocity"
""",
        encoding="utf-8",
    )
    return path


async def _plots(browser: HeadlessChromium) -> dict[str, Any]:
    result: dict[str, Any] = await browser.evaluate(PLOT_CHECK)
    return result


@needs_chromium
@pytest.mark.asyncio
async def test_live_page_follows_the_daemon_and_recovers_from_a_restart(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    pub = f"tcp://127.0.0.1:{_free_port()}"
    cfg_path = _daemon_config(
        tmp_path / "daemon.toml", run_dir, pub, f"tcp://127.0.0.1:{_free_port()}"
    )
    scenario = write_scenario(
        tmp_path / "scenario.toml", scenario_data(frame_period_s=32.0, thermal=True)
    )
    sim_port = _free_port()
    # One 32 s frame per wall second.
    sim = _Process(
        ["sim", "serve", "--port", str(sim_port), "--scenario", str(scenario), "--speed", "32"],
        tmp_path / "sim.log",
    )
    daemon_args = [
        "run",
        "--config",
        str(cfg_path),
        "--instrument",
        f"socket://127.0.0.1:{sim_port}",
    ]
    daemon = _Process(daemon_args, tmp_path / "daemon.log")
    config = parse_config({"service": {"heartbeat_interval_s": 0.2}})
    dash = Dashboard(
        run_dir=run_dir,
        pub_endpoint=pub,
        config=config,
        port=0,
        store_poll_s=0.5,
        wait_for_store=True,
    )
    sim.start()
    try:
        await asyncio.sleep(1.0)
        daemon.start()
        async with dash, HeadlessChromium() as browser, aiohttp.ClientSession() as http:
            await browser.goto(dash.url)
            await browser.wait_for(
                "window.afmdriftDashboard && Object.keys(window.afmdriftDashboard.frameShown)"
                ".length >= 3",
                timeout_s=60,
            )
            # A second browser (a bare WebSocket client) watches at the same time.
            async with http.ws_connect(dash.url + "ws") as second:
                first = json.loads((await second.receive(timeout=30)).data)
                assert first["type"] == "snapshot"
                kinds = set()
                async with asyncio.timeout(30):
                    while "frames" not in kinds:
                        kinds.add(json.loads((await second.receive()).data)["type"])
                assert dash.pages == 2

            # Every plot rendered and holds data (offsets and channels need a tick).
            await browser.wait_for(
                "document.querySelector('#plot-frame .heatmaplayer .hm') !== null"
                " || document.getElementById('frame-note').textContent.includes('re-measured')",
                timeout_s=30,
            )
            await asyncio.sleep(1.0)
            plots = await _plots(browser)
            for plot in PLOTS:
                assert plots[plot]["svg"] > 0, (plot, plots)
                assert plots[plot]["points"] > 0, (plot, plots)
            link = await browser.evaluate("document.getElementById('daemon-link').textContent")
            assert link.startswith("live from"), link

            # New frames keep appearing, each timed from its publication (how
            # fast is a benchmark's figure, benchmarks/bench_dashboard.py: on a
            # busy machine a test may only ask that they arrive).
            n0 = await browser.evaluate("window.afmdriftDashboard.latenciesMs.length")
            await browser.wait_for(
                f"window.afmdriftDashboard.latenciesMs.length >= {n0 + 3}", timeout_s=60
            )
            latencies = await browser.evaluate("window.afmdriftDashboard.latenciesMs")
            assert all(0.0 <= v < 60_000.0 for v in latencies[n0:]), latencies
            shot = await browser.screenshot(tmp_path / "dashboard-live.png")
            _save_screenshot(shot, "dashboard-live.png")

            # Kill the daemon: the page says so; restart it: the page follows again.
            last_seq = await browser.evaluate(
                "Math.max(...Object.keys(window.afmdriftDashboard.frameShown).map(Number))"
            )
            daemon.kill()
            await browser.wait_for(
                "document.getElementById('daemon-link').textContent.includes('silent')",
                timeout_s=30,
            )
            daemon.start()
            await browser.wait_for(
                "Math.max(...Object.keys(window.afmdriftDashboard.frameShown).map(Number))"
                f" > {last_seq + 1}",
                timeout_s=60,
            )
            await browser.wait_for(
                "document.getElementById('daemon-link').textContent.startsWith('live from')",
                timeout_s=30,
            )
            assert await browser.evaluate("window.afmdriftDashboard.lastError") is None
            assert browser.errors == []
    finally:
        daemon.kill()
        sim.kill()


def _log_lines(log: Path) -> list[str]:
    return log.read_text(encoding="utf-8").splitlines() if log.exists() else []


async def _first_lines(log: Path, proc: _Process, n: int, timeout_s: float = 30.0) -> list[str]:
    """The first ``n`` lines a process wrote to its log (fails if it exits first)."""
    async with asyncio.timeout(timeout_s):
        while len(lines := _log_lines(log)) < n:
            assert proc.proc is not None
            assert proc.proc.poll() is None, "\n".join(lines)
            await asyncio.sleep(0.05)
    return lines[:n]


@needs_chromium
@pytest.mark.asyncio
async def test_dashboard_started_before_the_daemon_waits_and_then_follows_the_run(
    tmp_path: Path,
) -> None:
    """Regression (issue 31): ``afmdrift dashboard --run-dir RUN --pub ...``
    started before ``afmdrift run`` (a service unit, a script that starts both)
    ended with "no such run directory". It now waits, says for which path (in
    its output and on the page), and shows the run once the daemon has made it:
    the directory, then the store, then its frames."""
    run_dir = tmp_path / "run"
    store = run_dir / "run.sqlite"
    pub = f"tcp://127.0.0.1:{_free_port()}"
    cfg_path = _daemon_config(
        tmp_path / "daemon.toml", run_dir, pub, f"tcp://127.0.0.1:{_free_port()}"
    )
    scenario = write_scenario(
        tmp_path / "scenario.toml", scenario_data(frame_period_s=32.0, thermal=True)
    )
    sim_port = _free_port()
    sim = _Process(
        ["sim", "serve", "--port", str(sim_port), "--scenario", str(scenario), "--speed", "32"],
        tmp_path / "sim.log",
    )
    dash_log = tmp_path / "dashboard.log"
    dashboard = _Process(
        [
            *("dashboard", "--config", str(cfg_path), "--run-dir", str(run_dir)),
            *("--pub", pub, "--port", str(_free_port())),
        ],
        dash_log,
    )
    daemon = _Process(
        ["run", "--config", str(cfg_path), "--instrument", f"socket://127.0.0.1:{sim_port}"],
        tmp_path / "daemon.log",
    )
    dashboard.start()
    sim.start()
    try:
        first, second = await _first_lines(dash_log, dashboard, 2)
        assert first.startswith("afmdrift dashboard: http://127.0.0.1:"), first
        assert f"following {pub}; run directory {run_dir}" in first
        assert second.startswith(f"afmdrift dashboard: waiting for {store} ("), second
        assert "no such run directory" in second
        url = first.split()[2]

        async with HeadlessChromium() as browser:
            await browser.goto(url)
            await browser.wait_for(
                "!document.getElementById('store-link').hidden && document.getElementById"
                f"('store-link').textContent === {json.dumps(f'waiting for {store}')}",
                timeout_s=30,
            )
            store_text = await browser.evaluate("document.getElementById('store-text').textContent")
            assert store_text.startswith(f"waiting for {store} ("), store_text
            link = await browser.evaluate("document.getElementById('daemon-link').textContent")
            assert link == f"waiting for the daemon on {pub}", link
            # Left in the test's directory to look at (not a figure of docs/).
            await browser.screenshot(tmp_path / "dashboard-waiting.png")
            # Several store polls find nothing; the dashboard keeps serving.
            await asyncio.sleep(2.5)
            assert not run_dir.exists()
            assert dashboard.proc is not None
            assert dashboard.proc.poll() is None

            daemon.start()
            await browser.wait_for(
                "window.afmdriftDashboard && Object.keys(window.afmdriftDashboard.frameShown)"
                ".length >= 3",
                timeout_s=90,
            )
            await browser.wait_for("document.getElementById('store-link').hidden", timeout_s=10)
            store_text = await browser.evaluate("document.getElementById('store-text').textContent")
            assert store_text == f"{store} (read-only)"
            # The run store is followed: channels and events exist only there.
            await browser.wait_for(
                "document.getElementById('plot-channels').data.some("
                "(t) => (t.x || []).length > 0 && t.name !== 'events')",
                timeout_s=15,
            )
            link = await browser.evaluate("document.getElementById('daemon-link').textContent")
            assert link.startswith("live from"), link
            await browser.screenshot(tmp_path / "dashboard-after-wait.png")
            assert await browser.evaluate("window.afmdriftDashboard.lastError") is None
            assert browser.errors == []
        assert dashboard.proc.poll() is None
    finally:
        daemon.kill()
        dashboard.kill()
        sim.kill()
    assert not any("Traceback" in line for line in _log_lines(dash_log))


@needs_chromium
@pytest.mark.asyncio
async def test_finished_replay_shows_the_whole_run(tmp_path: Path) -> None:
    session = tmp_path / "session"
    scenario = REPO / "config" / "scenarios" / "hidden" / "humidity.toml"
    assert main(["sim", "record", str(scenario), "--out", str(session), "--frames", "12"]) == 0
    config = parse_config(
        {
            "registration": {"block_size": 32, "extended_size": 96},
            "service": {"archive_frames": True},
            "model": {"predictor": "constant_velocity"},
        }
    )
    run_dir = tmp_path / "run"
    replay_session(session, run_dir, config=config)
    # A stand-in in the documented format (docs/diagnostics.md): a real diagnosis
    # needs far more frames than this test replays.
    finding = "Stand-in diagnose result written by the test: missing effect humidity."
    (run_dir / "diagnosis.json").write_text(
        json.dumps({"finding": finding, "config": '[model.physics]\nterms = ["humidity"]'}),
        encoding="utf-8",
    )
    sess, truth = load_session(session)
    assert truth is not None
    async with (
        Dashboard(run_dir=run_dir, truth=truth, session=sess, port=0) as dash,
        HeadlessChromium() as browser,
    ):
        await browser.goto(dash.url)
        await browser.wait_for(
            "window.afmdriftDashboard && window.afmdriftDashboard.snapshots > 0"
            " && document.getElementById('frame-note').textContent.includes('re-measured')",
            timeout_s=60,
        )
        await browser.wait_for(
            "document.getElementById('diagnosis-finding').textContent.includes('humidity')",
            timeout_s=10,
        )
        await asyncio.sleep(0.5)
        plots = await _plots(browser)
        frames = await browser.evaluate(
            "document.getElementById('plot-drift').data.filter((t) => t.name === 'measured p')"
            ".map((t) => t.x.length)"
        )
        assert frames == [12, 12]  # x and y: every frame of the run
        truth_points = await browser.evaluate(
            "document.getElementById('plot-drift').data.filter((t) => t.name === 'true drift')"
            ".map((t) => t.x.length)"
        )
        assert len(truth_points) == 2
        assert min(truth_points) > 12
        for plot in PLOTS:
            assert plots[plot]["points"] > 0, (plot, plots)
        # d(t) of a finished run: rebuilt from the stored curves, said so on the page
        note = await browser.evaluate("document.getElementById('offset-note').textContent")
        assert "rebuilt from the" in note
        assert "offset curves kept in the run store" in note
        config_line = await browser.evaluate(
            "document.getElementById('diagnosis-config').textContent"
        )
        assert 'terms = ["humidity"]' in config_line
        shot = await browser.screenshot(tmp_path / "dashboard-replay.png")
        _save_screenshot(shot, "dashboard-replay.png")
        assert browser.errors == []


def test_demo_serves_the_dashboard_and_ends_its_summary_with_the_address(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "demo-run"
    assert main(["demo", "--frames", "3", "--size", "128", "--run-dir", str(run)]) == 0
    lines = capsys.readouterr().out.splitlines()
    started = [ln for ln in lines if ln.startswith("dashboard: http://127.0.0.1:")]
    assert len(started) == 1
    url = started[0].removeprefix("dashboard: ")
    assert lines[-1].startswith(f"  dashboard: {url} (stops with the demo;")
