"""The daemon diagnoses its own run in a child process, beside the frames.

Through the real transports: the simulator on loopback TCP, the production
driver, the daemon's PUB and control sockets, and the child process that is
``afmdrift diagnose RUN_DIR --snapshot --json``.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import zmq.asyncio
from service_sim import REPO, SimProcess, driver, running_service, service_config, sim_server

from afmdrift.client import Subscriber, control
from afmdrift.config import AfmdriftConfig
from afmdrift.drivers.sim import load_scenario
from afmdrift.service import DIAGNOSES_FILE, read_diagnoses
from afmdrift.wire import DiagnosisMsg, FrameMsg

pytestmark = [pytest.mark.asyncio]

HIDDEN = REPO / "config" / "scenarios" / "hidden"


def live_config(run_dir: Path, **service: Any) -> AfmdriftConfig:
    """The default model (physics) on the hidden-effect scenarios' small frames."""
    return service_config(
        run_dir, model={}, registration={"block_size": 32, "extended_size": 96}, **service
    )


async def _until(condition: Callable[[], bool], *, poll_s: float = 0.05) -> None:
    """Return once ``condition()`` holds (bound it with a timeout)."""
    for _ in itertools.count():
        if condition():
            return
        await asyncio.sleep(poll_s)


async def _frames_until(sub: Subscriber, want: Any) -> list[Any]:
    """Messages received until ``want(msg)`` is true (bound it with a timeout)."""
    got = []
    while True:
        msg = await sub.recv()
        got.append(msg)
        if want(msg):
            return got


async def test_live_diagnosis_runs_beside_the_daemon_stored_and_published(tmp_path: Path) -> None:
    """Every 12 frames a diagnosis comes on topic ``diagnosis``, the same object
    ``afmdrift diagnose --json`` prints, with its frame range; it is stored in the
    run directory; the ``diagnose`` command starts one (no token) and a second
    request while it runs is skipped; no frame waits for it."""
    ctx = zmq.asyncio.Context()
    scenario = load_scenario(HIDDEN / "control.toml")
    run_dir = tmp_path / "run"
    try:
        async with sim_server(scenario, speed=300.0) as (_, url):
            cfg = live_config(run_dir, diagnose_every_frames=12)
            async with running_service(cfg, driver(url), ctx) as service:
                sub = Subscriber(service.pub_endpoint, ctx=ctx, topics=["frame", "diagnosis"])
                try:
                    async with asyncio.timeout(150):
                        got = await _frames_until(sub, lambda m: isinstance(m, DiagnosisMsg))
                    first = got[-1]
                    assert isinstance(first, DiagnosisMsg)
                    frames = [m for m in got if isinstance(m, FrameMsg)]
                    assert first.reason == "every"
                    assert first.first_frame == 0
                    assert 11 <= first.last_frame <= frames[-1].frame
                    dg = first.diagnosis
                    assert dg["frame_range"] == [first.first_frame, first.last_frame]
                    assert dg["model_effects"] == list(cfg.model.physics.terms)
                    assert isinstance(dg["plain_finding"], str)
                    assert dg["plain_finding"]
                    th = dg["thresholds"]
                    assert th["look"] == first.look
                    assert th["alpha"] < th["run_alpha"]
                    # Stored as published.
                    assert read_diagnoses(run_dir)[-1] == first

                    # On request, without a token; a second while it runs is skipped.
                    endpoint = service.control_endpoint
                    for _ in range(20):
                        # A periodic diagnosis may start between the wait and
                        # the request (a frame a second here, a diagnosis
                        # several seconds on a busy machine): then ask again.
                        await _until(lambda: not service.diagnosis.running)
                        one = await control(endpoint, "diagnose", ctx=ctx)
                        if one.started:
                            break
                    two = await control(endpoint, "diagnose", ctx=ctx)
                    assert one.started is True
                    assert two.started is False
                    async with asyncio.timeout(120):
                        got = await _frames_until(
                            sub, lambda m: isinstance(m, DiagnosisMsg) and m.reason == "request"
                        )
                    asked = got[-1]
                    assert asked.look > first.look  # periodic looks may come between
                    assert asked.last_frame >= first.last_frame
                    # The frames went on while it ran: none lost, none twice.
                    seen = [m.frame for m in got if isinstance(m, FrameMsg)]
                    assert seen == list(range(seen[0], seen[0] + len(seen)))
                finally:
                    sub.close()
        stored = read_diagnoses(run_dir)
        assert [m.look for m in stored] == list(range(1, len(stored) + 1))
    finally:
        ctx.term()


async def test_failing_and_timed_out_diagnoses_are_skipped_and_the_daemon_goes_on(
    tmp_path: Path,
) -> None:
    """A diagnosis that cannot run (a run still too short: ``diagnose`` exits 1)
    and one that outlives ``diagnose_timeout_s`` (killed) are skipped: no result
    stored or published, no child left, and frames keep coming."""
    ctx = zmq.asyncio.Context()
    scenario = load_scenario(HIDDEN / "control.toml")
    run_dir = tmp_path / "run"
    try:
        async with sim_server(scenario, speed=300.0) as (_, url):
            cfg = live_config(run_dir, diagnose_every_frames=2, diagnose_timeout_s=0.3)
            async with running_service(cfg, driver(url), ctx) as service:
                async with asyncio.timeout(120):
                    # Frames 2, 4, 6: too short, or killed at 0.3 s; both skipped.
                    await service.wait_for_frames(8)
                    await _until(
                        lambda: service.diagnosis.failed >= 2 and not service.diagnosis.running
                    )
                    await service.wait_for_frames(service.frames_processed + 2)
                assert service.diagnosis.looks == 0
                assert not (run_dir / DIAGNOSES_FILE).exists()
                assert _children(os.getpid(), "diagnose") == []
                reply = await control(service.control_endpoint, "status", ctx=ctx)
                assert reply.status is not None
                assert reply.status.state == "running"
    finally:
        ctx.term()


def _children(pid: int, word: str) -> list[int]:
    """Live processes whose parent is ``pid`` and whose command line holds ``word``."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == pid and fields[0] != "Z" and word in cmdline:
            out.append(int(entry.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux")
async def test_no_orphan_diagnosis_after_the_daemon_is_killed(tmp_path: Path) -> None:
    """SIGKILL the daemon (``afmdrift run``) while its diagnosis runs: the child dies too."""
    scenario_file = tmp_path / "control.toml"
    scenario_file.write_text((HIDDEN / "control.toml").read_text(encoding="utf-8"))
    sim = SimProcess(scenario_file, speed=300.0)
    url = sim.start()
    run_dir = tmp_path / "run"
    config = tmp_path / "afmdrift.toml"
    config.write_text(
        "[service]\n"
        'pub_endpoint = "tcp://127.0.0.1:*"\ncontrol_endpoint = "tcp://127.0.0.1:*"\n'
        f'run_dir = "{run_dir}"\nframe_poll_interval_s = 0.05\n'
        "diagnose_every_frames = 1\ndiagnose_timeout_s = 600.0\n"
        "[registration]\nblock_size = 32\nextended_size = 96\n",
        encoding="utf-8",
    )
    daemon = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "afmdrift", "run", "--config", str(config), "--instrument", url,
        cwd=REPO, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    child: list[int] = []
    try:

        def started() -> bool:
            if not child:
                child.extend(_children(daemon.pid, "diagnose"))
            return bool(child) or daemon.returncode is not None

        async with asyncio.timeout(120):
            await _until(started)
        assert child, "no live diagnosis started"
        daemon.send_signal(signal.SIGKILL)
        await asyncio.wait_for(daemon.wait(), 30)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(10):
                await _until(lambda: not _alive(child[0]))
        assert not _alive(child[0]), f"diagnosis {child[0]} outlived its daemon"
    finally:
        if daemon.returncode is None:
            daemon.kill()
            await asyncio.wait_for(daemon.wait(), 30)
        for pid in child:
            with contextlib.suppress(ProcessLookupError):
                if _alive(pid):
                    os.kill(pid, signal.SIGKILL)
        sim.kill()
