"""``afmdrift run`` says what it serves and, at the stop, what it did: against
``afmdrift sim serve`` on a loopback port, both subprocesses as a user runs
them, stopped with SIGTERM."""

from __future__ import annotations

import ctypes
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
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


# --------------------------------------------------------------------------- cannot start

#: prctl(PR_CAPBSET_DROP) and the capabilities that let root write whatever the
#: permission bits say (linux/prctl.h, linux/capability.h).
_PR_CAPBSET_DROP = 24
_CAP_DAC_OVERRIDE = 1
_CAP_DAC_READ_SEARCH = 2


def _drop_root_override() -> None:
    """In the daemon's process, before it runs afmdrift: root gives up overriding
    permission bits (the capabilities leave its bounding set, so the exec does
    not grant them), and a directory of mode 0o555 is read-only for it as for
    any other user."""
    libc = ctypes.CDLL(None, use_errno=True)
    for cap in (_CAP_DAC_OVERRIDE, _CAP_DAC_READ_SEARCH):
        if libc.prctl(_PR_CAPBSET_DROP, cap, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP) refused")


def _read_only(directory: Path) -> Callable[[], None] | None:
    """Make ``directory`` read-only for the daemon; return what its process must
    run first (root's capabilities dropped), or skip where that cannot be had."""
    directory.chmod(0o555)
    preexec = _drop_root_override if os.geteuid() == 0 else None
    probe = subprocess.run(
        [sys.executable, "-c", "import sys; open(sys.argv[1], 'w')", str(directory / "probe")],
        preexec_fn=preexec,
        capture_output=True,
        check=False,
    )
    if probe.returncode == 0:
        (directory / "probe").unlink()
        pytest.skip(f"{directory} stays writable for this user even at mode 0o555")
    return preexec


def _start(
    tmp_path: Path, service: str, preexec: Callable[[], None] | None = None
) -> subprocess.CompletedProcess[str]:
    """``afmdrift run`` with ``[service]`` settings ``service`` (run_dir and both
    endpoints on loopback unless given), on an instrument it never reaches: each
    case fails while the daemon starts, before it connects."""
    defaults = {
        "run_dir": f'"{tmp_path / "run"}"',
        "pub_endpoint": '"tcp://127.0.0.1:*"',
        "control_endpoint": '"tcp://127.0.0.1:*"',
    }
    for key, value in defaults.items():
        if f"{key} =" not in service:
            service += f"\n{key} = {value}"
    config = tmp_path / "afmdrift.toml"
    config.write_text(f"[service]\n{service}\n", encoding="utf-8")
    return subprocess.run(
        [sys.executable, "-m", "afmdrift", "run", "--config", str(config),
         "--instrument", "/dev/null"],
        cwd=REPO, capture_output=True, text=True, timeout=60, preexec_fn=preexec, check=False,
    )  # fmt: skip


def _one_line(proc: subprocess.CompletedProcess[str], *named: str) -> str:
    """The single error line of a daemon that could not start (exit status 2)."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("afmdrift: error: "), lines[0]
    for name in named:
        assert name in lines[0], lines[0]
    assert "drift service on" not in proc.stdout
    return lines[0]


@pytest.mark.parametrize("run_dir", ["new", "existing", "resumed"])
def test_run_cannot_start_on_a_read_only_run_directory(tmp_path: Path, run_dir: str) -> None:
    """A run directory the daemon cannot write (new in a read-only folder, empty,
    or holding an earlier run) ends it at once with one line, exit status 2."""
    parent = tmp_path / "runs"
    parent.mkdir()
    run = parent / "run"
    if run_dir == "existing":
        run.mkdir()
    if run_dir == "resumed":
        RunStore(run).close()
    try:
        preexec = _read_only(parent if run_dir == "new" else run)
        proc = _start(tmp_path, f'run_dir = "{run}"', preexec)
    finally:
        parent.chmod(0o755)
        if run.is_dir():
            run.chmod(0o755)
    expected = "cannot create run directory" if run_dir == "new" else "is not writable"
    _one_line(proc, str(run), expected)


@pytest.mark.parametrize("key", ["pub_endpoint", "control_endpoint"])
def test_run_cannot_start_when_its_port_is_in_use(tmp_path: Path, key: str) -> None:
    """Another program listening on the publish or control port ends the daemon
    at once with one line naming the setting and the address."""
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        endpoint = f"tcp://127.0.0.1:{held.getsockname()[1]}"
        proc = _start(tmp_path, f'{key} = "{endpoint}"')
    _one_line(proc, f"service.{key}", endpoint, "in use")


@pytest.mark.parametrize("where", ["missing", "a file", "read-only"])
def test_run_cannot_start_without_a_writable_token_directory(tmp_path: Path, where: str) -> None:
    """Regression: a control token file in a directory that does not exist was
    made with its directories; one under a file or in a read-only directory
    ended the daemon with a traceback (exit status 1). Each is one line naming
    service.control_token_file, exit status 2, and nothing is created."""
    folder = tmp_path / "tokens"
    if where == "a file":
        folder.write_text("not a directory", encoding="utf-8")
    if where == "read-only":
        folder.mkdir()
    token = folder / "control.token"
    try:
        preexec = _read_only(folder) if where == "read-only" else None
        proc = _start(tmp_path, f'control_token_file = "{token}"', preexec)
    finally:
        if folder.is_dir():
            folder.chmod(0o755)
    _one_line(proc, "service.control_token_file", str(token))
    assert not token.exists()
    assert folder.is_dir() == (where == "read-only")
