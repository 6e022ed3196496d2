"""What the machine does to the daemon: a full disk, and a failure in each step
of the frame path (acquire, register, model, store, publish, reference files).

The daemon runs on a loopback simulator and publishes on loopback ZeroMQ; the
status is read through the control socket, as a user's script would.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import shutil
import subprocess
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
import zmq
import zmq.asyncio
from service_sim import driver, running_service, service_config, sim_server, small_scenario

from afmdrift.client import Subscriber, control
from afmdrift.runs import RunStore
from afmdrift.service import DriftService
from afmdrift.wire import FrameMsg, OffsetMsg, StatusMsg

pytestmark = pytest.mark.slow


def _check_store(run_dir: Path, frames: int) -> None:
    """Every frame the daemon processed is stored once, in order, intact."""
    with RunStore(run_dir) as store:
        assert store.check_consistency() == []
        seqs = [r.seq for r in store.frames()]
    assert seqs == list(range(frames))


async def _status(service: DriftService) -> StatusMsg:
    reply = await control(service.control_endpoint, "status", timeout_s=5.0)
    assert reply.status is not None
    return reply.status


async def _offsets_flow(service: DriftService, ctx: zmq.asyncio.Context, n: int) -> None:
    """``n`` valid offset samples arrive, in sequence, from the live daemon."""
    sub = Subscriber(service.pub_endpoint, topics=("offset",), ctx=ctx)
    try:
        seqs: list[int] = []
        async with asyncio.timeout(20):
            while len(seqs) < n:
                msg = await sub.recv()
                assert isinstance(msg, OffsetMsg)
                if msg.valid:
                    seqs.append(msg.seq)
        assert seqs == list(range(seqs[0], seqs[0] + n))
    finally:
        sub.close()


async def _wait(predicate: Any, timeout_s: float, poll_s: float = 0.05) -> None:
    async with asyncio.timeout(timeout_s):
        while not predicate():  # noqa: ASYNC110 - the daemon has no event for this
            await asyncio.sleep(poll_s)


@contextlib.contextmanager
def _small_filesystem(where: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` mounted at ``where`` (root only; skipped otherwise)."""
    where.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a small file system needs root (CI runs as root)")
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip()})")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def _fill_disk(path: Path) -> None:
    """Write ``path`` until the file system has no space left."""
    with path.open("wb", buffering=0) as fh:
        for size in (65536, 512):
            with pytest.raises(OSError, match="No space left"):  # noqa: PT012
                while True:
                    fh.write(b"\0" * size)


@contextlib.asynccontextmanager
async def _daemon(run_dir: Path, **service: Any) -> AsyncIterator[DriftService]:
    ctx = zmq.asyncio.Context()
    try:
        async with (
            sim_server(small_scenario(), speed=40.0) as (_, url),
            running_service(service_config(run_dir, **service), driver(url), ctx) as svc,
        ):
            svc.ctx = ctx
            yield svc
    finally:
        ctx.term()


@pytest.mark.asyncio
async def test_a_full_file_system_neither_stops_the_daemon_nor_loses_a_frame(
    tmp_path: Path,
) -> None:
    """The run directory on a 3 MB file system that fills up after a few frames:
    the daemon goes on measuring and publishing, says why in its status, and
    stores every held frame, in order, once space returns. (Before: it exited
    with status 1 on ``sqlite3.OperationalError: database or disk is full``.)"""
    with _small_filesystem(tmp_path / "disk", "3m") as disk:
        run = disk / "run"
        async with _daemon(run, archive_frames=True) as service:
            async with asyncio.timeout(30):
                await service.wait_for_frames(4)
            await asyncio.to_thread(_fill_disk, disk / "filler")
            full_at = service.frames_processed
            async with asyncio.timeout(30):
                await service.wait_for_frames(full_at + 4)
            status = await _status(service)
            assert "store_error" in status.flags
            assert status.store_problem is not None
            assert str(run / "run.sqlite") in status.store_problem
            assert status.frames_held >= 2
            assert service.ctx is not None
            await _offsets_flow(service, service.ctx, 50)
            (disk / "filler").unlink()
            await _wait(lambda: "store_error" not in service.flags, 20)
            status = await _status(service)
            assert status.store_problem is None
            assert status.frames_held == 0
            assert status.frames_unstored == 0
            processed = service.frames_processed
        _check_store(run, processed)
        with RunStore(run) as store:
            archived = sorted(p.name for p in (run / "frames").glob("*.npy"))
            assert archived == [f"{s:06d}.npy" for s in range(processed)]
            assert len(store.channels()) > 0


def _full(db: Any) -> None:
    """SQLite's ENOSPC: no page may be added, and the last pages' space is taken."""
    db.execute("CREATE TABLE IF NOT EXISTS filler (b BLOB)")
    pages = db.execute("PRAGMA page_count").fetchone()[0]
    db.execute(f"PRAGMA max_page_count = {pages}")
    for size in (4000, 400, 40, 4):
        with contextlib.suppress(Exception):
            while True:
                db.execute("INSERT INTO filler VALUES (zeroblob(?))", (size,))


def _space(db: Any) -> None:
    db.execute("PRAGMA max_page_count = 1073741823")
    db.execute("DROP TABLE filler")


@pytest.mark.asyncio
async def test_a_store_that_cannot_write_holds_its_frames_in_bounded_memory(
    tmp_path: Path,
) -> None:
    """The same without root: SQLite's own full-disk error. A bound that holds
    only a few frames' images: images go first, positions stay, and the
    frames are all stored when the store writes again."""
    run = tmp_path / "run"
    async with _daemon(run, archive_frames=True, store_hold_mb=1.0) as service:
        async with asyncio.timeout(30):
            await service.wait_for_frames(3)
        store = service._store
        assert store is not None
        await service._in_worker(lambda: _full(store._db))
        full_at = service.frames_processed
        async with asyncio.timeout(40):
            await service.wait_for_frames(full_at + 20)
        status = await _status(service)
        assert "store_error" in status.flags
        assert "database or disk is full" in (status.store_problem or "")
        assert status.frames_held >= 10
        assert status.frames_unstored == 0
        await service._in_worker(lambda: _space(store._db))
        await _wait(lambda: "store_error" not in service.flags, 20)
        writer = service._writer
        assert writer is not None
        images_dropped = writer.images_dropped
        processed = service.frames_processed
    _check_store(run, processed)
    # 1 MB held 128² images (64 kB each) for a few frames only: the rest went
    assert images_dropped >= 5
    archived = len(list((run / "frames").glob("*.npy")))
    assert processed - images_dropped <= archived < processed


class _Once:
    """Raise ``error`` on the ``at``-th call, pass every other call on."""

    def __init__(self, fn: Any, error: BaseException, at: int) -> None:
        self.fn, self.error, self.at, self.calls = fn, error, at, 0

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.calls += 1
        if self.calls == self.at:
            raise self.error
        return self.fn(*args, **kwargs)


@pytest.mark.asyncio
@pytest.mark.parametrize(
    "step", ["acquire", "register", "model", "store", "reference_file", "publish"]
)
async def test_a_failure_in_any_step_of_the_frame_path_does_not_end_the_daemon(
    tmp_path: Path, step: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One injected failure in one step of one frame (the instrument's own
    faults, garbled or late replies, are the simulator's:
    tests/integration/test_service_faults.py): the daemon says so, and the
    frames after it are measured, stored and published."""
    run = tmp_path / "run"
    async with _daemon(run) as service:
        async with asyncio.timeout(30):
            await service.wait_for_frames(3)
        pipeline = service.pipeline
        if step == "acquire":
            # a driver's bug, not an instrument error: the call is failed and retried
            instrument = service.instrument
            monkeypatch.setattr(
                instrument,
                "latest_frame",
                _Once(instrument.latest_frame, ValueError("injected"), 1),
            )
        elif step == "register":
            positions = pipeline.positions
            monkeypatch.setattr(
                positions, "locate", _Once(positions.locate, RuntimeError("injected"), 1)
            )
        elif step == "model":
            predictor = pipeline.predictor
            monkeypatch.setattr(
                predictor, "update", _Once(predictor.update, FloatingPointError("injected"), 1)
            )
        elif step == "store":
            store = service._store
            assert store is not None
            monkeypatch.setattr(
                store,
                "record_frame",
                _Once(store.record_frame, OSError(errno.EIO, "injected I/O error"), 1),
            )
        elif step == "reference_file":
            import afmdrift.runs._store as store_module

            monkeypatch.setattr(
                store_module,
                "save_image",
                _Once(store_module.save_image, OSError(errno.ENOSPC, "injected"), 1),
            )
            await service._in_worker(pipeline.request_reset)
        else:
            publisher = service.publishing.publisher
            assert publisher is not None
            real_send = publisher.send

            async def send(msg: Any) -> None:
                if isinstance(msg, FrameMsg) and not sent_failure:
                    sent_failure.append(msg)
                    raise zmq.ZMQError(errno.EAGAIN, "injected")
                await real_send(msg)

            sent_failure: list[Any] = []
            monkeypatch.setattr(publisher, "send", send)
        before = service.frames_processed
        async with asyncio.timeout(40):
            await service.wait_for_frames(before + 3)
        status = await _status(service)
        assert "frame_error" not in status.flags
        assert "instrument_error" not in status.flags
        assert "store_error" not in status.flags
        if step in ("register", "model"):
            assert status.frames_failed == 1
        else:
            assert status.frames_failed == 0
        assert service.ctx is not None
        await _offsets_flow(service, service.ctx, 20)
        processed = service.frames_processed
    # a frame whose processing failed is neither stored nor numbered
    _check_store(run, processed)
