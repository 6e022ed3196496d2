"""The daemon's store writer: frames a store cannot write (a full disk) are held in
bounded memory and written, in order and whole, once it can again.

The full disk is SQLite's own: ``PRAGMA max_page_count`` at the database's
size, with its free space taken, makes every write fail with "database or
disk is full", exactly the error a full file system gives; raising it again
is the space coming back. (The
daemon on a real full file system: tests/integration/test_service_machine.py.)
"""

from __future__ import annotations

import logging
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from test_store import make_record

from afmdrift.model import FeedBatch
from afmdrift.pipeline import FrameOutcome
from afmdrift.records import ChannelSample, Event, EventKind, LoggedEvent
from afmdrift.runs import HeldWrites, RunStore
from afmdrift.runs._store import UNSTORED_KEY


def _outcome(seq: int, *, reference: bool = False, image_px: int = 64) -> FrameOutcome:
    image = np.full((image_px, image_px), float(seq), dtype=np.float32)
    return FrameOutcome(
        record=make_record(seq),
        curve=None,
        curve_dict={"curve": seq},
        predictor_name="p",
        predictor_state={"state": [seq] * 100},
        field=None,
        reference=image if reference else None,
        image=image,
        low_confidence=False,
        history=FeedBatch(
            channels=[ChannelSample(t_s=10.0 * seq, values={"temperature_c": 20.0 + seq})],
            events=[LoggedEvent(0, seq, Event(10.0 * seq + 1, EventKind.OFFSET_MOVE, 1.0, 0.0))],
        ),
    )


def _fill(store: RunStore) -> None:
    """The disk is full: no page can be added to the database, and the last
    pages' free space is taken too (a filler table, as another file would)."""
    db = store._db
    db.execute("CREATE TABLE filler (b BLOB)")
    pages = db.execute("PRAGMA page_count").fetchone()[0]
    db.execute(f"PRAGMA max_page_count = {pages}")
    for size in (4000, 400, 40, 4):
        try:
            while True:
                db.execute("INSERT INTO filler VALUES (zeroblob(?))", (size,))
        except sqlite3.OperationalError:
            pass


def _free(store: RunStore) -> None:
    """Space again: the filler goes, and the database may grow."""
    store._db.execute("PRAGMA max_page_count = 1073741823")
    store._db.execute("DROP TABLE filler")


def test_frames_held_while_the_disk_is_full_are_written_in_order_once_it_is_not(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with RunStore(tmp_path, archive_frames=True) as store:
        writer = HeldWrites(store, max_bytes=100_000_000, archive=True)
        for seq in range(3):
            writer.record(_outcome(seq, reference=seq == 0))
        assert writer.problem is None
        assert writer.held == 0
        _fill(store)
        with caplog.at_level(logging.WARNING, logger="afmdrift.runs._record"):
            for seq in range(3, 40):
                writer.record(_outcome(seq, reference=seq == 20))
                writer.set_meta({"instrument_serial": f"S{seq}"})
            assert writer.problem is not None
            assert str(store.path) in writer.problem
            assert "database or disk is full" in writer.problem
            # (the free space left in the tables' last pages takes a few first)
            stored = [r.seq for r in store.frames()]
            assert stored == list(range(len(stored)))
            assert len(stored) <= 20
            assert writer.held == 40 - len(stored)
            assert writer.flush() is False
            _free(store)
            assert writer.flush() is True
        errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(errors) == 1, "the failure is said once"
        assert f"writes again: {40 - len(stored)} held frame(s) written" in caplog.text
        assert writer.problem is None
        assert writer.held == 0
        records = store.frames()
        assert [r.seq for r in records] == list(range(40))
        assert records[25] == make_record(25)
        assert store.check_consistency() == []
        assert store.meta()["instrument_serial"] == "S39"
        assert store.meta()["reference_seq"] == "20"
        assert len(store.channels()) == 40
        assert [e.log_index for e in store.events()] == list(range(40))
        assert store.curve(39) == {"curve": 39}
    assert (tmp_path / "frames" / "000039.npy").is_file()
    assert not (tmp_path / "reference-000000.npy").exists()
    assert (tmp_path / "reference-000020.npy").is_file()


def test_past_the_bound_images_go_before_positions_and_every_loss_is_counted(
    tmp_path: Path,
) -> None:
    image_bytes = 128 * 128 * 4
    with RunStore(tmp_path, archive_frames=True) as store:
        writer = HeldWrites(store, max_bytes=30 * image_bytes, archive=True)
        writer.record(_outcome(0, reference=True, image_px=128))
        _fill(store)
        for seq in range(1, 61):
            writer.record(_outcome(seq, image_px=128, reference=seq % 10 == 0))
        # 60 frames of one image each fit only without their archived images:
        # those went, every position is still held
        assert writer.held >= 40
        assert writer.frames_dropped == 0
        assert writer.images_dropped >= 20
        for seq in range(61, 2000):
            writer.record(_outcome(seq, image_px=128, reference=seq % 10 == 0))
        # now whole frames, oldest first, and their logs move on
        assert writer.frames_dropped > 0
        first_held = 2000 - writer.held - writer.frames_dropped
        _free(store)
        assert writer.flush()
        seqs = [r.seq for r in store.frames()]
        assert seqs == [
            *range(first_held),
            *range(first_held + writer.frames_dropped, 2000),
        ]
        assert store.check_consistency() == []
        unstored = store.meta()[UNSTORED_KEY]
        assert unstored == f"{first_held}-{first_held + writer.frames_dropped - 1}"
        # no channel or event was lost with the frames let go
        assert len(store.channels()) == 2000
        assert len(store.events()) == 2000
        # the newest held reference was kept
        assert store.meta()["reference_seq"] == "1990"


def test_a_frame_that_cannot_be_written_leaves_nothing_half_written(tmp_path: Path) -> None:
    """An image file that fails (ENOSPC from the file system) keeps the frame
    whole in memory, and the retry writes it once."""
    with RunStore(tmp_path, archive_frames=True) as store:
        writer = HeldWrites(store, max_bytes=100_000_000, archive=True)
        writer.record(_outcome(0, reference=True))
        # the archive directory cannot be written (a file in its way)
        frames = tmp_path / "frames"
        for f in frames.iterdir():
            f.unlink()
        frames.rmdir()
        frames.write_bytes(b"")
        writer.record(_outcome(1))
        assert writer.held == 1
        assert "frames" in (writer.problem or "")
        assert [r.seq for r in store.frames()] == [0]
        frames.unlink()
        writer.record(_outcome(2))
        assert [r.seq for r in store.frames()] == [0, 1, 2]
        assert len(store.channels()) == 3
        assert store.check_consistency() == []


def test_a_frame_the_store_already_has_is_reported_not_retried(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with RunStore(tmp_path) as store:
        writer = HeldWrites(store, max_bytes=1_000_000, archive=False)
        writer.record(_outcome(0))
        with caplog.at_level(logging.ERROR):
            writer.record(_outcome(0))
        assert writer.held == 0
        assert writer.problem is None
        assert "frame 0 not written" in caplog.text


def test_sqlite_full_is_the_error_a_full_file_system_gives(tmp_path: Path) -> None:
    """The injection above raises what SQLite raises on ENOSPC."""
    with RunStore(tmp_path) as store:
        _fill(store)
        error = None
        for seq in range(100):
            try:
                store.record_frame(make_record(seq), predictor="p", predictor_state={}, curve=None)
            except sqlite3.OperationalError as err:
                error = str(err)
                break
        assert error == "database or disk is full"
        assert store.check_consistency() == []
