"""Frames that must not touch the reference, and restarts from a damaged or
changed run store (issue "A daemon that cannot be knocked over")."""

from __future__ import annotations

import dataclasses
import logging
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from service_sim import service_config, small_scenario

from afmdrift.drivers import Frame
from afmdrift.drivers.sim import SimulatedAFM
from afmdrift.drivers.sim._record import record_session
from afmdrift.pipeline import FramePipeline
from afmdrift.service import RunStore, replay_session


def _frames(sim: SimulatedAFM, n: int) -> list[Frame]:
    out: list[Frame] = []
    while len(out) < n:
        out.extend(sim.advance_to(sim.now_s + 8.0))
    return out[:n]


def _replayed_run(tmp_path: Path, frames: int = 8) -> Path:
    session = tmp_path / "session"
    record_session(small_scenario(), session, frames=frames)
    run = tmp_path / "run"
    replay_session(session, run, config=service_config(tmp_path / "unused"))
    return run


@pytest.mark.parametrize("bad", ["one_pixel", "other_shape_nan"])
def test_a_bad_frame_of_another_shape_keeps_the_reference(tmp_path: Path, bad: str) -> None:
    """Regression: a 1x1 frame, or an invalid frame of another shape, replaced the
    registration reference before it was validated: a silent permanent
    position error (one bad frame in three lost the whole y drift)."""
    sim = SimulatedAFM(small_scenario(drift_nm_per_sqrt_s=0.1, warmup_nm=(100.0, 60.0)))
    frames = _frames(sim, 6)
    clean = FramePipeline(config=service_config(tmp_path / "a"))
    want = [clean.process(f, seq=k).record for k, f in enumerate(frames)]
    pipe = FramePipeline(config=service_config(tmp_path / "b"))
    got = []
    for k, f in enumerate(frames):
        if k == 3:
            if bad == "one_pixel":
                image = np.zeros((1, 1))
            else:
                image = np.full((f.shape[0] // 2, f.shape[1] // 2), np.nan)
            broken = dataclasses.replace(f, heights_nm=image)
            rec = pipe.process(broken, seq=k).record
            assert rec.reason.startswith("registration failed")
            assert not rec.fed_model
        got.append(pipe.process(f, seq=k).record)
    for w, g in zip(want[4:], got[4:], strict=True):
        assert g.reason == w.reason
        assert (g.x_nm, g.y_nm) == pytest.approx((w.x_nm, w.y_nm), abs=1e-9)


def test_restart_with_a_changed_predictor_starts_it_fresh(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Regression: restarting a run dir after changing [model] predictor gave a
    KeyError traceback; now that predictor starts fresh on the kept
    observations, and the log says so."""
    run = _replayed_run(tmp_path)
    with RunStore(run) as store:
        state = store.resume_state()
        records = store.last_frames(100)
    assert state is not None
    cfg = service_config(tmp_path / "unused")
    stored = state.predictor
    assert stored == cfg.model.predictor
    cfg = cfg.model_copy(update={"model": cfg.model.model_copy(update={"predictor": "kalman"})})
    pipe = FramePipeline(config=cfg)
    with caplog.at_level(logging.WARNING):
        pipe.resume(state, records=records, channels=[], events=[])
    assert pipe.predictor.name == "kalman"
    assert pipe.n_fed == sum(r.fed_model for r in records)
    assert pipe.curve is not None
    assert f"model state is for predictor {stored!r}" in caplog.text
    assert "started fresh" in caplog.text


def test_damaged_model_state_row_is_reported_and_skipped(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Regression: a garbled model-state row stopped start-up with a traceback."""
    run = _replayed_run(tmp_path)
    with sqlite3.connect(run / "run.sqlite") as db:
        newest = db.execute("SELECT MAX(seq) FROM model_state").fetchone()[0]
        db.execute("UPDATE model_state SET state_json = '{\"trunc' WHERE seq = ?", (newest,))
    with caplog.at_level(logging.WARNING), RunStore(run) as store:
        state = store.resume_state()
    assert state is not None
    assert state.predictor_state is not None  # the row before the damaged one
    assert f"model state of frame {newest} is damaged" in caplog.text


@pytest.mark.parametrize("damage", ["empty", "truncated", "not_an_image"])
def test_damaged_reference_image_means_a_new_reference(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, damage: str
) -> None:
    """Regression: an empty or truncated reference .npy stopped start-up with a
    traceback; now the next frame becomes the reference (reported)."""
    run = _replayed_run(tmp_path)
    (ref,) = run.glob("reference-*.npy")
    data = ref.read_bytes()
    if damage == "empty":
        ref.write_bytes(b"")
    elif damage == "truncated":
        ref.write_bytes(data[: len(data) // 2])
    else:
        np.save(ref, np.zeros(5, dtype=np.float32))
    with caplog.at_level(logging.WARNING), RunStore(run) as store:
        state = store.resume_state()
    assert state is not None
    assert state.reference is None
    assert "taking a new one" in caplog.text


def test_a_held_frame_is_measured_and_recorded_but_does_not_feed_the_model(
    tmp_path: Path,
) -> None:
    sim = SimulatedAFM(small_scenario(drift_nm_per_sqrt_s=0.1))
    frames = _frames(sim, 4)
    pipe = FramePipeline(config=service_config(tmp_path))
    outs = [pipe.process(f, seq=k) for k, f in enumerate(frames[:3])]
    held = pipe.process(frames[3], seq=3, hold="event log unreadable up to this frame")
    assert held.record.reason == "event log unreadable up to this frame"
    assert not held.record.fed_model
    assert held.record.valid  # measured: its image position is known
    assert not held.low_confidence
    assert pipe.n_fed == sum(o.record.fed_model for o in outs)
