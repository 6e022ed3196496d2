"""Run store: frames commit atomically, resume state survives a crash, CSV columns."""

from __future__ import annotations

import csv
import math
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from afmdrift.drivers import ChannelSample, Event, EventKind
from afmdrift.pipeline import MEASUREMENT_COLUMNS, FrameRecord
from afmdrift.service import RunStore, StoreError


def make_record(seq: int, **changes: object) -> FrameRecord:
    values: dict[str, object] = {
        "seq": seq,
        "instrument_frame": seq,
        "epoch": 0,
        "t_start_s": 10.0 * seq,
        "t_end_s": 10.0 * seq + 5.0,
        "t_mid_s": 10.0 * seq + 2.5,
        "direction": "up",
        "rows": 64,
        "cols": 64,
        "pixel_x_nm": 2.0,
        "pixel_y_nm": 2.0,
        "dx_nm": 0.5,
        "dy_nm": -0.25,
        "image_x_nm": 0.5 * seq,
        "image_y_nm": -0.25 * seq,
        "x_nm": 0.5 * seq,
        "y_nm": -0.25 * seq,
        "sigma_nm": 0.1,
        "valid": True,
        "fed_model": True,
        "reason": "",
        "valid_blocks": 9,
        "total_blocks": 9,
        "keyframe_index": 0,
        "reanchored": False,
        "pred_x_nm": float("nan") if seq == 0 else 0.5 * seq + 0.1,
        "pred_y_nm": float("nan") if seq == 0 else -0.25 * seq,
        "pred_sigma_nm": float("nan") if seq == 0 else 0.3,
        "offset_x_nm": 0.0,
        "offset_y_nm": 0.0,
        "wall_s": 1.7e9 + seq,
        "latency_s": 0.01,
        "field_json": "{}",
    }
    values.update(changes)
    return FrameRecord(**values)  # type: ignore[arg-type]


def test_frames_round_trip_with_nan_as_null(tmp_path: Path) -> None:
    with RunStore(tmp_path) as store:
        for seq in range(3):
            store.record_frame(
                make_record(seq), predictor="p", predictor_state={"k": seq}, curve={"c": seq}
            )
        back = store.frames()
        assert store.curve(2) == {"c": 2}
    assert [r.seq for r in back] == [0, 1, 2]
    assert math.isnan(back[0].pred_x_nm)
    assert back[1] == make_record(1)
    with sqlite3.connect(tmp_path / "run.sqlite") as db:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert db.execute("SELECT pred_x_nm FROM frames WHERE seq = 0").fetchone()[0] is None


def test_channels_and_events_are_committed_with_the_next_frame(tmp_path: Path) -> None:
    store = RunStore(tmp_path)
    store.add_channels(ChannelSample(t_s=1.0, values={"temperature_c": 22.0, "humidity_pct": 40}))
    store.add_event(epoch=0, log_index=0, event=Event(2.0, EventKind.OFFSET_MOVE, 1.0, 0.0))
    reader = RunStore(tmp_path)
    assert reader.channels() == []
    assert reader.events() == []
    store.record_frame(make_record(0), predictor="p", predictor_state=None, curve=None)
    chans = reader.channels()
    assert chans[0].values == {"temperature_c": 22.0, "humidity_pct": 40.0}
    assert reader.events() == [(0, 0, Event(2.0, EventKind.OFFSET_MOVE, 1.0, 0.0))]
    # A repeated log entry (re-read after a reconnect) is stored once.
    store.add_event(epoch=0, log_index=0, event=Event(2.0, EventKind.OFFSET_MOVE, 1.0, 0.0))
    store.record_frame(make_record(1), predictor="p", predictor_state=None, curve=None)
    assert len(reader.events()) == 1
    store.close()
    reader.close()


def test_failed_frame_transaction_leaves_no_partial_rows(tmp_path: Path) -> None:
    """A frame that fails mid-write commits nothing of itself; what was queued
    with it stays queued (a full disk must not lose the channel log), and goes
    with the next frame that commits."""
    with RunStore(tmp_path) as store:
        store.record_frame(make_record(0), predictor="p", predictor_state={}, curve=None)
        store.add_channels(ChannelSample(t_s=3.0, values={"temperature_c": 21.0}))
        with pytest.raises(sqlite3.IntegrityError):
            store.record_frame(
                make_record(0),
                predictor="p",
                predictor_state={},
                curve=None,
                channels=[ChannelSample(t_s=4.0, values={"temperature_c": 22.0})],
            )
        assert store.frame_count() == 1
        assert store.check_consistency() == []
        assert store.channels() == []
        store.record_frame(make_record(1), predictor="p", predictor_state={}, curve=None)
    with RunStore(tmp_path) as store:
        # the queued sample, not the one given with the failed call
        assert [c.t_s for c in store.channels()] == [3.0]


def test_resume_state_holds_model_reference_and_event_cursor(tmp_path: Path) -> None:
    ref = np.arange(16, dtype=np.float32).reshape(4, 4)
    with RunStore(tmp_path) as store:
        store.add_event(epoch=0, log_index=0, event=Event(1.0, EventKind.POWER_ON))
        store.add_event(epoch=0, log_index=1, event=Event(2.0, EventKind.TIP_CHANGE))
        store.record_frame(
            make_record(0), predictor="p", predictor_state={"w": [1]}, curve=None, reference=ref
        )
        store.record_frame(make_record(1), predictor="p", predictor_state={"w": [2]}, curve=None)
    with RunStore(tmp_path) as store:
        state = store.resume_state()
    assert state is not None
    assert state.last.seq == 1
    assert state.predictor_state == {"w": [2]}
    assert state.reference_seq == 0
    assert state.reference is not None
    np.testing.assert_array_equal(state.reference, ref)
    assert state.event_cursor == 2


def test_store_of_another_schema_version_is_refused(tmp_path: Path) -> None:
    RunStore(tmp_path).close()
    with sqlite3.connect(tmp_path / "run.sqlite") as db:
        db.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    with pytest.raises(StoreError, match="schema version 99"):
        RunStore(tmp_path)


def test_measurements_csv_has_documented_columns(tmp_path: Path) -> None:
    with RunStore(tmp_path) as store:
        for seq in range(2):
            store.record_frame(make_record(seq), predictor="p", predictor_state=None, curve=None)
        path = store.write_measurements_csv()
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == MEASUREMENT_COLUMNS
    assert rows[0]["pred_x_nm"] == ""
    assert float(rows[1]["t_s"]) == 12.5
    assert float(rows[1]["pred_error_nm"]) == pytest.approx(0.1)


def test_sigkill_between_frames_loses_at_most_the_frame_in_flight(tmp_path: Path) -> None:
    """Crash consistency: a writer killed with SIGKILL mid-stream leaves a readable
    store whose frames are exactly 0..n-1 with their model states."""
    script = textwrap.dedent(
        f"""
        import os, signal, sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_store import make_record
        from afmdrift.runs import RunStore
        import numpy as np
        store = RunStore({str(tmp_path)!r}, archive_frames=True)
        for seq in range(40):
            store.record_frame(make_record(seq), predictor="p", predictor_state={{"s": seq}},
                               curve=None, image=np.zeros((8, 8)),
                               reference=np.full((8, 8), seq, np.float32))
            if seq == 25:
                os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], check=False, timeout=120)
    assert proc.returncode == -9
    with RunStore(tmp_path) as store:
        assert store.check_consistency() == []
        n = store.frame_count()
        state = store.resume_state()
    assert n == 26
    assert state is not None
    assert state.predictor_state == {"s": 25}
    assert state.reference is not None
    assert state.reference[0, 0] == 25
    assert len(list((tmp_path / "frames").glob("*.npy"))) == 26
