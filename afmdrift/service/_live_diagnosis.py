"""The daemon diagnoses its own run, beside it, in another process.

Every ``service.diagnose_every_frames`` frames, and on the ``diagnose``
control command, :class:`LiveDiagnosis` runs

``python -m afmdrift diagnose RUN_DIR --snapshot --json --look K --workers 1
--effects <the daemon's terms now> [--config <its file>]``

as a child process: the very command a user types, so the live diagnosis is
``afmdrift diagnose`` and not a copy of it (and the service imports nothing
of :mod:`afmdrift.diagnostics`; the layers stay as they are). ``--snapshot``
makes the child copy the run store with SQLite's online backup API in one
read transaction, so it reads the store as it stood after one frame's
commit, while the daemon goes on writing (WAL: readers never block the
writer). The child runs at the lowest CPU priority and with one worker, so
the frames, the offset stream and the control replies keep their pace; the
event loop only waits for its output.

At most one runs at a time: a request while one runs is skipped (logged).
A child that fails (its status and the last line it wrote to stderr are
logged; a run still too short exits 1 and is only noted) or outlives
``service.diagnose_timeout_s`` (killed) is skipped, and the daemon goes on.
A child dies with the daemon: ``prctl(PR_SET_PDEATHSIG, SIGKILL)`` is set
in the child before it runs, so even a SIGKILL of the daemon leaves no
orphan (Linux; elsewhere the child is killed when the daemon stops, but not
after a SIGKILL).

``K``, the look, counts the diagnoses of this run that gave a result, from
1, resumed from the run directory: the diagnoses of a growing run are a
sequence of tests on the same data, and the ``K``-th is tested at its share
of the false-alarm level (``docs/diagnostics.md``, *Repeated diagnoses*).

Each result is appended, as its ``diagnosis`` wire message (JSON, one line),
to ``RUN_DIR/diagnoses.jsonl`` (:data:`DIAGNOSES_FILE`), then published.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import logging
import os
import signal
import sys
import time
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from typing import Literal

from afmdrift._bounded import loads_json
from afmdrift.config import ServiceConfig
from afmdrift.wire import MAX_PAYLOAD_BYTES, DiagnosisMsg

__all__ = [
    "DIAGNOSES_FILE",
    "LiveDiagnosis",
    "diagnose_command",
    "last_diagnosis",
    "read_diagnoses",
]

log = logging.getLogger(__name__)

#: The run directory's file of live diagnoses, one ``diagnosis`` message per line.
DIAGNOSES_FILE = "diagnoses.jsonl"

#: ``afmdrift diagnose`` exits 1 when the run is still too short (TooFewFramesError).
_TOO_FEW_FRAMES = 1
_PR_SET_PDEATHSIG = 1

Reason = Literal["every", "request"]


def diagnose_command(
    run_dir: str | Path,
    *,
    look: int,
    effects: Sequence[str],
    config_path: str | Path | None,
) -> list[str]:
    """The command line of one live diagnosis of ``run_dir`` (see the module docstring)."""
    cmd = [sys.executable, "-m", "afmdrift", "diagnose", str(run_dir), "--snapshot", "--json"]
    cmd += ["--look", str(look), "--workers", "1"]
    if effects:
        cmd += ["--effects", ",".join(effects)]
    if config_path is not None:
        cmd += ["--config", str(config_path)]
    return cmd


def read_diagnoses(run_dir: str | Path) -> list[DiagnosisMsg]:
    """The live diagnoses stored in ``run_dir``, oldest first (a line that is not
    one, such as a torn last line of a daemon killed while appending, is left out)."""
    return [m for m in map(_parse_line, _lines(run_dir)) if m is not None]


def last_diagnosis(run_dir: str | Path) -> DiagnosisMsg | None:
    """The newest live diagnosis stored in ``run_dir``, or None."""
    for line in reversed(_lines(run_dir)):
        msg = _parse_line(line)
        if msg is not None:
            return msg
    return None


def _lines(run_dir: str | Path) -> list[bytes]:
    try:
        return (Path(run_dir) / DIAGNOSES_FILE).read_bytes().splitlines()
    except FileNotFoundError:
        return []


def _parse_line(line: bytes) -> DiagnosisMsg | None:
    if len(line) > MAX_PAYLOAD_BYTES:
        return None
    try:
        return DiagnosisMsg.model_validate_json(line)
    except ValueError:
        return None


def _die_with_parent(parent: int) -> Callable[[], None]:
    """The child's set-up before it runs: killed when the daemon dies, lowest priority.

    libc is opened here, in the daemon: between fork and exec (the daemon has
    threads) the child only calls into it, it loads nothing."""
    libc = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None

    def setup() -> None:
        if libc is not None:
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
            # The daemon may have died before the line above: then nobody is
            # left to be told, and the child is an orphan already.
            if os.getppid() != parent:
                os._exit(1)
        os.nice(19)

    return setup


class LiveDiagnosis:
    """One diagnosis of the run at a time, in a child process; results stored and published.

    Parameters
    ----------
    config : ServiceConfig
        ``run_dir``, ``diagnose_every_frames``, ``diagnose_timeout_s``.
    effects : callable
        The daemon's physics terms now (they change with ``reload_model``).
    config_path : callable
        The daemon's configuration file now, or None (the default configuration).
    publish : callable
        Sends a :class:`DiagnosisMsg` on the PUB socket.
    run_id : str
        The daemon's run id (carried by the message).
    epoch : callable
        The instrument link's current epoch (carried by the message).

    Attributes
    ----------
    looks : int
        Diagnoses of this run that gave a result, the stored ones included.
    skipped : int
        Requests skipped because a diagnosis was running.
    failed : int
        Diagnoses that failed or timed out since the daemon started.
    """

    def __init__(
        self,
        config: ServiceConfig,
        *,
        effects: Callable[[], Sequence[str]],
        config_path: Callable[[], Path | None],
        publish: Callable[[DiagnosisMsg], Awaitable[None]],
        run_id: str,
        epoch: Callable[[], int] = lambda: 0,
    ) -> None:
        self.config = config
        self.run_dir = Path(config.run_dir)
        self._effects = effects
        self._config_path = config_path
        self._publish = publish
        self._run_id = run_id
        self._epoch = epoch
        self._wanted = asyncio.Event()
        self._reason: Reason = "every"
        self.running = False
        self.looks = 0
        self.skipped = 0
        self.failed = 0
        self._seq = 0
        self.last: DiagnosisMsg | None = None

    def resume(self) -> None:
        """Count the diagnoses the run directory holds (their looks are spent)."""
        stored = read_diagnoses(self.run_dir)
        if stored:
            self.last = stored[-1]
            self.looks = max(m.look for m in stored)

    def frame_done(self, frames: int) -> None:
        """A frame was processed; ``frames`` of this run so far."""
        every = self.config.diagnose_every_frames
        if every > 0 and frames > 0 and frames % every == 0:
            self.request("every")

    def request(self, reason: Reason) -> bool:
        """Start a diagnosis unless one runs or waits to; True if this request starts one."""
        if self.running or self._wanted.is_set():
            self.skipped += 1
            log.info("live diagnosis (%s) skipped: one is running", reason)
            return False
        self._reason = reason
        self._wanted.set()
        return True

    async def loop(self) -> None:
        """Run the requested diagnoses one after the other, for ever."""
        while True:
            await self._wanted.wait()
            self.running = True
            self._wanted.clear()
            try:
                await self._once(self._reason)
            finally:
                self.running = False

    async def _once(self, reason: Reason) -> None:
        """One diagnosis; any failure is logged and the loop goes on."""
        look = self.looks + 1
        cmd = diagnose_command(
            self.run_dir, look=look, effects=list(self._effects()), config_path=self._config_path()
        )
        t0 = time.monotonic()
        try:
            proc = await asyncio.create_subprocess_exec(
                *cmd,
                stdin=asyncio.subprocess.DEVNULL,
                stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.PIPE,
                preexec_fn=_die_with_parent(os.getpid()),
            )
        except OSError as err:
            self.failed += 1
            log.error("live diagnosis not started (%s); the daemon goes on", err)
            return
        log.info("live diagnosis %d started (pid %d, %s)", look, proc.pid, reason)
        try:
            out, stderr = await asyncio.wait_for(
                proc.communicate(), timeout=self.config.diagnose_timeout_s
            )
        except TimeoutError:
            await _kill(proc)
            self.failed += 1
            log.error(
                "live diagnosis %d killed after service.diagnose_timeout_s = %g s; skipped, "
                "the daemon goes on",
                look, self.config.diagnose_timeout_s,
            )  # fmt: skip
            return
        except asyncio.CancelledError:
            await _kill(proc)
            raise
        duration_s = time.monotonic() - t0
        if proc.returncode != 0:
            why = _last_line(stderr)
            if proc.returncode == _TOO_FEW_FRAMES:
                log.info("live diagnosis %d: not yet (%s)", look, why)
            else:
                self.failed += 1
                log.error(
                    "live diagnosis %d failed (exit status %s: %s); skipped, the daemon goes on",
                    look, proc.returncode, why,
                )  # fmt: skip
            return
        try:
            msg = self._message(out, look=look, reason=reason, duration_s=duration_s)
        except ValueError as problem:
            self.failed += 1
            log.error("live diagnosis %d: unusable output (%s); skipped", look, problem)
            return
        try:
            await asyncio.to_thread(self._store, msg)
        except OSError as problem:
            log.error("live diagnosis %d: not stored in %s (%s)", look, self.run_dir, problem)
        self.looks = look
        self.last = msg
        self._seq += 1
        await self._publish(msg)
        log.info(
            "live diagnosis %d (frames %d-%d) in %.1f s: %s",
            look, msg.first_frame, msg.last_frame, duration_s,
            msg.diagnosis.get("plain_finding", ""),
        )  # fmt: skip

    def _message(self, out: bytes, *, look: int, reason: Reason, duration_s: float) -> DiagnosisMsg:
        """The wire message of the child's JSON output (ValueError if it is not one)."""
        if len(out) > MAX_PAYLOAD_BYTES // 2:
            raise ValueError(f"{len(out)} bytes of JSON; at most {MAX_PAYLOAD_BYTES // 2}")
        doc = loads_json(out, what="diagnose --json")
        if not isinstance(doc, dict):
            raise ValueError("diagnose --json did not print a JSON object")
        frames = doc.get("frame_range")
        if not (isinstance(frames, list) and len(frames) == 2):
            raise ValueError("diagnose --json gave no frame_range")
        return DiagnosisMsg(
            seq=self._seq,
            run_id=self._run_id,
            epoch=self._epoch(),
            wall_s=time.time(),
            look=look,
            first_frame=int(frames[0]),
            last_frame=int(frames[1]),
            reason=reason,
            duration_s=duration_s,
            diagnosis=doc,
        )

    def _store(self, msg: DiagnosisMsg) -> None:
        line = msg.model_dump_json() + "\n"
        with (self.run_dir / DIAGNOSES_FILE).open("a", encoding="utf-8") as fh:
            fh.write(line)
            fh.flush()
            os.fsync(fh.fileno())


async def _kill(proc: asyncio.subprocess.Process) -> None:
    """Kill ``proc`` and reap it (never leave a zombie or an orphan)."""
    with contextlib.suppress(ProcessLookupError):
        proc.kill()
    await asyncio.shield(proc.wait())


def _last_line(err: bytes) -> str:
    lines = [ln for ln in err.decode("utf-8", "replace").splitlines() if ln.strip()]
    return lines[-1].strip()[:500] if lines else "no message"
