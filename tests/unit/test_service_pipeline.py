"""The per-frame pipeline and replay: bad frames, low confidence, reference reset,
commanded offset moves, reload, and measurements.csv.

Frames come from the simulator (in process, no wire); the expected drift
positions come from the simulator's truth.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from service_sim import service_config, small_scenario

from afmdrift.drivers import Frame
from afmdrift.drivers.sim import SimulatedAFM
from afmdrift.drivers.sim._record import record_session
from afmdrift.errors import InputError
from afmdrift.model import make_predictor, truth_frame_mean
from afmdrift.pipeline import MEASUREMENT_COLUMNS, FramePipeline
from afmdrift.service import RunStore, replay_session
from afmdrift.session import read_session, write_session


def _frames(sim: SimulatedAFM, n: int) -> list[Frame]:
    out: list[Frame] = []
    while len(out) < n:
        for f in sim.advance_to(sim.now_s + 8.0):
            out.append(f)
    return out[:n]


def _truth(sim: SimulatedAFM, frame: Frame) -> np.ndarray:
    t = np.linspace(frame.t_start_s, frame.t_end_s, 200)
    x, y = sim.truth_at(t)
    return truth_frame_mean(frame, t, np.stack([x, y], axis=1))


@pytest.fixture
def sim() -> SimulatedAFM:
    return SimulatedAFM(small_scenario(drift_nm_per_sqrt_s=0.1, warmup_nm=(100.0, 60.0)))


def test_nan_frame_is_recorded_and_skipped_without_disturbing_the_track(
    tmp_path: Path, sim: SimulatedAFM
) -> None:
    """Regression guard: NaN pixels must never crash the pipeline or reach the model."""
    pipe = FramePipeline(config=service_config(tmp_path))
    frames = _frames(sim, 6)
    bad = frames[3].heights_nm.copy()
    bad[10:20, 5:9] = np.nan
    outs = []
    for k, f in enumerate(frames):
        if k == 3:
            f = dataclasses.replace(f, heights_nm=bad)
        outs.append(pipe.process(f, seq=k))
    nan_rec = outs[3].record
    assert not nan_rec.fed_model
    assert nan_rec.reason.startswith("registration failed")
    assert math.isnan(nan_rec.x_nm)
    assert outs[3].low_confidence
    assert outs[3].predictor_state is None
    assert all(o.record.fed_model for k, o in enumerate(outs) if k != 3)
    ref = _truth(sim, frames[0])
    for k in (4, 5):
        want = _truth(sim, frames[k]) - ref
        got = np.array([outs[k].record.x_nm, outs[k].record.y_nm])
        np.testing.assert_allclose(got, want, atol=1.0)


def test_low_confidence_frames_do_not_feed_the_model(tmp_path: Path, sim: SimulatedAFM) -> None:
    cfg = service_config(tmp_path, min_valid_blocks=1000)
    pipe = FramePipeline(config=cfg)
    outs = [pipe.process(f, seq=k) for k, f in enumerate(_frames(sim, 4))]
    assert outs[0].record.reason == "reference"
    for o in outs[1:]:
        assert not o.record.fed_model
        assert "low confidence" in o.record.reason
        assert "service.min_valid_blocks=1000" in o.record.reason
        assert o.low_confidence
        assert math.isfinite(o.record.x_nm)  # measured, recorded, just not trusted


def test_reset_reference_keeps_the_drift_position_continuous(
    tmp_path: Path, sim: SimulatedAFM
) -> None:
    pipe = FramePipeline(config=service_config(tmp_path))
    frames = _frames(sim, 10)
    outs = [pipe.process(f, seq=k) for k, f in enumerate(frames[:6])]
    pipe.request_reset()
    outs += [pipe.process(f, seq=k + 6) for k, f in enumerate(frames[6:])]
    reset = outs[6].record
    assert reset.reason == "new reference (position estimated)"
    assert not reset.fed_model
    assert outs[6].reference is not None
    # the new reference's position continues the drift trajectory of the
    # frames before it (it has no measurement of its own), and it reports no
    # trajectory samples
    assert outs[6].trajectory is None
    ref = _truth(sim, frames[0])
    pred_err = math.hypot(*(np.array([reset.x_nm, reset.y_nm]) - (_truth(sim, frames[6]) - ref)))
    for k in (8, 9):
        want = _truth(sim, frames[k]) - ref
        got = np.array([outs[k].record.x_nm, outs[k].record.y_nm])
        # after the reset, errors are those of the estimate plus a measurement
        assert math.hypot(*(got - want)) < pred_err + 1.0


def _behind_increments_nm(records: list) -> np.ndarray:  # type: ignore[type-arg]
    """|p_k − p_ref − Σ increments| of each frame after ``records[0]`` (the
    chain's reference), nm."""
    p = np.array([[r.x_nm, r.y_nm] for r in records])
    steps = np.cumsum([[r.dx_nm, r.dy_nm] for r in records[1:]], axis=0)
    return np.hypot(*(p[1:] - p[0] - steps).T)


def test_positions_after_an_estimated_reference_follow_their_increments(
    tmp_path: Path, sim: SimulatedAFM
) -> None:
    """Regression (issue 42): after a new reference whose position is
    estimated, the later frames re-estimated that position, and the stored
    positions fell behind the sum of the measured increments frame after
    frame (0.35 nm after 13 frames here; 2.7 nm after 27 in the daemon).
    Now the estimate is held: the new chain follows its increments as the
    first one does, its σ is the estimate's and the chain's own in
    root-sum-square, and the chain is numbered."""
    pipe = FramePipeline(config=service_config(tmp_path))
    frames = _frames(sim, 20)
    outs = [pipe.process(f, seq=k) for k, f in enumerate(frames[:6])]
    pipe.request_reset()
    outs += [pipe.process(f, seq=k + 6) for k, f in enumerate(frames[6:])]
    records = [o.record for o in outs]
    assert [o.position.chain for o in outs if o.position] == [0] * 6 + [1] * 14
    first, second = records[:6], records[6:]
    assert second[0].reason == "new reference (position estimated)"
    # as closely as the first chain (the trajectory at mid-scan time is not
    # the sum of the registration's increments), and not drifting away
    limit = max(0.1, 2.0 * float(_behind_increments_nm(first).max()))
    assert _behind_increments_nm(second).max() < limit
    sigma_ref = second[0].sigma_nm
    assert math.isfinite(sigma_ref)
    assert sigma_ref > 0.1
    own = np.sqrt([r.sigma_nm**2 - sigma_ref**2 for r in second[1:]])
    chain0 = np.array([r.sigma_nm for r in first[1:]])
    assert np.all(own < 3.0 * chain0.max())


def test_commanded_offset_moves_are_removed_from_the_drift_position(
    tmp_path: Path, sim: SimulatedAFM
) -> None:
    """A +Δ offset move shifts the image by −Δ; p must not jump with it."""
    pipe = FramePipeline(config=service_config(tmp_path))
    frames = _frames(sim, 3)
    sim.set_offset(40.0, -24.0)
    frames += _frames(sim, 4)[1:]  # the first frame may straddle the move
    pipe.push((), sim.events)
    outs = [pipe.process(f, seq=k) for k, f in enumerate(frames)]
    ref = _truth(sim, frames[0])
    last = outs[-1].record
    assert last.offset_x_nm == pytest.approx(40.0)
    assert last.image_x_nm == pytest.approx(last.x_nm - 40.0)
    for o, f in zip(outs[1:], frames[1:], strict=True):
        want = _truth(sim, f) - ref
        np.testing.assert_allclose([o.record.x_nm, o.record.y_nm], want, atol=1.5)


def test_reload_model_refits_on_the_kept_observations(tmp_path: Path, sim: SimulatedAFM) -> None:
    cfg = service_config(tmp_path, training_window=4)
    pipe = FramePipeline(config=cfg)
    for k, f in enumerate(_frames(sim, 7)):
        pipe.process(f, seq=k)
    assert len(pipe.observations) == 4
    n = pipe.reload_model(make_predictor("last_value"))
    assert n == 4
    assert pipe.predictor.name == "last_value"
    assert pipe.curve is not None
    last = pipe.observations[-1]
    np.testing.assert_allclose(
        pipe.predictor.predict([last.t_s + 100.0], pipe.history).mean_nm[0],
        [last.x_nm, last.y_nm],
    )


def _record(tmp_path: Path, n: int) -> Path:
    return record_session(
        small_scenario(drift_nm_per_sqrt_s=0.1, warmup_nm=(80.0, 40.0)),
        tmp_path / "session",
        frames=n,
    ).path


def test_replay_writes_store_and_documented_measurements_csv(tmp_path: Path) -> None:
    session = _record(tmp_path, 8)
    summary = replay_session(session, tmp_path / "run", config=service_config(tmp_path / "x"))
    assert summary.frames == 8
    assert summary.fed_model == 8
    with summary.measurements_csv.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == MEASUREMENT_COLUMNS
    assert [int(r["frame"]) for r in rows] == list(range(8))
    s = read_session(session)
    assert s.truth is not None
    ref = s.truth_at([float(rows[0]["t_s"])])[0]
    for r in rows[1:]:
        assert float(r["t_s"]) == pytest.approx(s.frame(int(r["frame"])).t_mid_s)
        want = s.truth_at([float(r["t_s"])])[0] - ref
        assert abs(float(r["x_nm"]) - want[0]) < 1.5
        assert abs(float(r["y_nm"]) - want[1]) < 1.5
    assert rows[0]["pred_x_nm"] == ""
    assert all(r["pred_x_nm"] != "" for r in rows[2:])
    with RunStore(tmp_path / "run") as store:
        assert store.check_consistency() == []
        assert store.frame_count() == 8
    with pytest.raises(InputError, match="already holds a run"):
        replay_session(session, tmp_path / "run", config=service_config(tmp_path / "x"))


def test_replay_survives_a_nan_frame_in_the_session(tmp_path: Path) -> None:
    path = _record(tmp_path, 6)
    s = read_session(path, mmap=False)
    frames = np.array(s.frames)
    frames[2, 0, 0] = np.nan
    write_session(dataclasses.replace(s, frames=frames), tmp_path / "nan-session")
    summary = replay_session(
        tmp_path / "nan-session", tmp_path / "run", config=service_config(tmp_path / "x")
    )
    assert summary.frames == 6
    assert summary.fed_model == 5
    with RunStore(tmp_path / "run") as store:
        rec = store.frames()[2]
    assert rec.reason.startswith("registration failed")


def test_the_model_is_fed_the_latest_sample_weighted_by_the_frames_own_registration(
    tmp_path: Path, sim: SimulatedAFM
) -> None:
    """Regression: the observation carried the trajectory's σ of p, which grows
    along the keyframe chain (and was the bias prior's for down frames), so
    as a weight it favoured early frames and one-step prediction got worse
    than before the trajectory. It now carries the registration's σ of the
    frame's block mean, at the time of the frame's latest trajectory sample."""
    pipe = FramePipeline(config=service_config(tmp_path))
    checked = 0
    for k, f in enumerate(_frames(sim, 5)):
        out = pipe.process(f, seq=k)
        rec, pos = out.record, out.position
        if k == 0 or out.trajectory is None:
            continue
        checked += 1
        assert pos is not None
        assert rec.fed_model
        assert rec.obs_t_s == pytest.approx(float(out.trajectory.t_s.max()))
        assert rec.obs_sigma_nm == pytest.approx(pos.measurement_sigma)
        assert rec.obs_sigma_nm != pytest.approx(rec.sigma_nm)
    assert checked >= 3


@pytest.mark.parametrize("n_valid", [0, 1, 2, 37])
def test_field_summary_is_the_mean_spread_and_median_of_the_valid_blocks(n_valid: int) -> None:
    """summarise_field (one compiled pass): the population mean and standard
    deviation of the valid blocks' vectors and their median confidence, in
    nm; invalid blocks (NaN vectors) never enter."""
    from types import SimpleNamespace

    from afmdrift.pipeline import summarise_field
    from afmdrift.registration import BlockField

    rng = np.random.default_rng(n_valid)
    n = 64
    valid = np.zeros(n, dtype=bool)
    valid[rng.choice(n, n_valid, replace=False)] = True
    vectors = rng.normal(3.0, 0.2, (n, 2)).astype(np.float32)
    vectors[~valid] = np.nan
    confidence = rng.uniform(0.0, 1.0, n).astype(np.float32)
    z = np.zeros((n, 2), dtype=np.float32)
    fld = BlockField(
        centres_px=z, vectors_px=vectors, confidence=confidence, mse=np.zeros(n),
        measured=valid.copy(), valid=valid, weight_centres_px=z,
    )  # fmt: skip
    summary = summarise_field(SimpleNamespace(field=fld), (2.0, 0.5))
    assert summary is not None
    assert (summary.total_blocks, summary.valid_blocks) == (n, n_valid)
    if n_valid == 0:
        assert summary.mean_dx_nm is None
        assert summary.median_confidence is None
        return
    good = vectors[valid].astype(np.float64)
    expected = (
        good[:, 0].mean() * 2.0, good[:, 1].mean() * 0.5,
        good[:, 0].std() * 2.0, good[:, 1].std() * 0.5,
        float(np.median(confidence[valid].astype(np.float64))),
    )  # fmt: skip
    got = (
        summary.mean_dx_nm, summary.mean_dy_nm, summary.std_dx_nm, summary.std_dy_nm,
        summary.median_confidence,
    )  # fmt: skip
    np.testing.assert_allclose(np.array(got, dtype=float), expected, rtol=1e-12, atol=1e-15)
    # the summary serialises as the wire model it is
    assert f'"valid_blocks":{n_valid}' in summary.model_dump_json()


def test_with_next_reads_one_frame_ahead() -> None:
    from afmdrift.pipeline._frame import with_next

    assert list(with_next([])) == []
    assert list(with_next(["a"])) == [(0, "a", None)]
    assert list(with_next(iter("abc"))) == [(0, "a", "b"), (1, "b", "c"), (2, "c", None)]


def test_passing_the_next_frame_changes_no_record(tmp_path: Path, sim: SimulatedAFM) -> None:
    """What a recording's tools (replay, evaluate, correct, measure) do:
    :meth:`FramePipeline.run` reads one frame ahead, so each frame's
    successor has its block pass run while the frame is placed. The records,
    with a bad frame among them, are those of the daemon's frame-by-frame
    calls."""
    frames = _frames(sim, 7)
    bad = frames[4].heights_nm.copy()
    bad[3, 3] = np.nan
    frames[4] = dataclasses.replace(frames[4], heights_nm=bad)
    plain = FramePipeline(config=service_config(tmp_path))
    ahead = FramePipeline(config=service_config(tmp_path))
    for k, (frame, outcome) in enumerate(zip(frames, ahead.run(frames), strict=True)):
        a = plain.process(frame, seq=k, t_now_s=frame.t_end_s).record
        b = outcome.record
        assert (a.x_nm, a.y_nm, a.fed_model, a.reason) == pytest.approx(
            (b.x_nm, b.y_nm, b.fed_model, b.reason), abs=0, nan_ok=True
        )
