"""``afmdrift run`` says what it serves and, at the stop, what it did: against
``afmdrift sim serve`` on a loopback port, both subprocesses as a user runs
them, stopped with SIGTERM."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from service_sim import REPO, SimProcess, committed_frames, scenario_data, write_scenario

from afmdrift.runs import RunStore

pytestmark = pytest.mark.slow


def _config(path: Path, run_dir: Path) -> Path:
    path.write_text(
        f"""
[service]
run_dir = "{run_dir}"
pub_endpoint = "tcp://127.0.0.1:*"
control_endpoint = "tcp://127.0.0.1:*"
frame_poll_interval_s = 0.05
clock_sync_interval_s = 0.1
reconnect_delay_s = 0.1

[registration]
block_size = 32
extended_size = 64

[model]
predictor = "physics"
physics = {{ terms = ["trend"] }}
""",
        encoding="utf-8",
    )
    return path


def test_run_prints_what_it_serves_and_a_summary_at_the_stop(tmp_path: Path) -> None:
    """Regression: ``afmdrift run`` printed nothing, at the start or the stop."""
    scenario = write_scenario(tmp_path / "scenario.toml", scenario_data(seed=5))
    run_dir = tmp_path / "run"
    sim = SimProcess(scenario, speed=100.0)
    daemon: subprocess.Popen[str] | None = None
    try:
        url = sim.start()
        daemon = subprocess.Popen(
            [sys.executable, "-m", "afmdrift", "run", "--config",
             str(_config(tmp_path / "afmdrift.toml", run_dir)), "--instrument", url],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        deadline = time.monotonic() + 60
        while committed_frames(run_dir) < 4:
            assert daemon.poll() is None, "afmdrift run exited early"
            assert time.monotonic() < deadline, "no frames recorded"
            time.sleep(0.1)
        daemon.send_signal(signal.SIGTERM)
        out, _ = daemon.communicate(timeout=30)
        assert daemon.returncode == 0
    finally:
        if daemon is not None and daemon.poll() is None:
            daemon.kill()
            daemon.communicate(timeout=30)
        sim.kill()

    lines = out.strip().splitlines()
    head, summary = "\n".join(lines[:-1]), lines[-1]
    assert f"instrument {url}" in head
    pub, control = re.findall(r"tcp://127\.0\.0\.1:(\d+)", head)  # the bound ports
    assert pub != control
    assert f"run directory {run_dir}" in head
    assert "predictor physics (terms: trend)" in head

    with RunStore(run_dir) as store:
        records = store.frames()
    valid = [r for r in records if r.valid]
    assert summary.startswith("afmdrift run: stopped after ")
    assert f"{len(records)} frames processed, {len(valid)} valid" in summary
    last = valid[-1]
    assert (
        f"last position x {last.x_nm:.2f} nm, y {last.y_nm:.2f} nm "
        f"(σ {last.sigma_nm:.2f} nm, frame {last.seq})"
    ) in summary
    assert summary.endswith(f"the run is in {run_dir}")
