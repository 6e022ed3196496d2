"""Drift trajectory on recorded simulator sessions, through ``afmdrift replay``."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from afmdrift.cli import main
from afmdrift.config import AfmdriftConfig, RegistrationConfig
from afmdrift.drivers.sim._record import record_session
from afmdrift.pipeline import dewarp_frame
from afmdrift.records import Frame
from afmdrift.registration import measure_drift
from afmdrift.runs import TRAJECTORY_COLUMNS
from afmdrift.service import replay_session
from afmdrift.session import read_session

CREEP = Path(__file__).parents[2] / "config" / "scenarios" / "hidden" / "creep.toml"


@pytest.fixture(scope="module")
def creep_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """20 frames of the hidden-creep scenario: offset moves of 100-200 nm
    (12-25 px) at 4000 s and 8500 s, with creep after each."""
    out = tmp_path_factory.mktemp("sessions") / "creep"
    record_session(CREEP, out, duration_s=6300.0)
    return out


def test_every_frame_after_offset_moves_is_accepted_and_on_the_truth(
    creep_session: Path, tmp_path: Path
) -> None:
    """Regression: frames after a logged offset move were measured without the
    move as their prior, and the blocks of frames whose drift changed during
    the scan were judged against one mean. Now the move places the windows,
    the blocks are judged against a trend over the rows, and each block row
    is a sample of the drift trajectory."""
    summary = replay_session(creep_session, tmp_path / "run", config=AfmdriftConfig())
    with summary.measurements_csv.open() as fh:
        rows = list(csv.DictReader(fh))
    assert all(r["reason"] in ("", "reference") for r in rows), [r["reason"] for r in rows]
    session = read_session(creep_session)
    assert any(e.kind.value == "offset_move" for e in session.events)
    assert session.truth is not None
    tt, tv = session.truth[:, 0], session.truth[:, 1:3]
    bias = np.asarray(
        json.loads((creep_session / "session.json").read_text())["simulator"][
            "scan_direction_bias_nm"
        ]
    )
    sign = {i: 1 if session.frame(i).direction.value == "up" else -1 for i in range(len(session))}
    t0 = session.frame(0).t_mid_s
    zero = np.array([np.interp(t0, tt, tv[:, 0]), np.interp(t0, tt, tv[:, 1])])
    with (tmp_path / "run" / "trajectory.csv").open() as fh:
        reader = csv.reader(fh)
        assert tuple(next(reader)) == TRAJECTORY_COLUMNS
        samples = np.array([[float(v) for v in row] for row in reader])
    frame = samples[:, 5].astype(int)
    assert set(frame) == set(range(1, len(session)))  # every measured frame
    assert np.bincount(frame)[1:].min() >= 2  # 128² frames, 64 px blocks
    true = np.column_stack(
        [np.interp(samples[:, 0], tt, tv[:, 0]), np.interp(samples[:, 0], tt, tv[:, 1])]
    )
    true += -zero + 0.5 * (np.array([sign[k] for k in frame]) - sign[0])[:, None] * bias
    err = samples[:, 1:3] - true
    # 0.055 nm before each block's window response was divided out and its
    # vector placed at its texture's scan time; 0.021 nm after
    assert np.sqrt(np.mean(err**2)) < 0.04
    # p of measurements.csv is the same curve at mid-scan time
    xy = np.array([[float(r["x_nm"]), float(r["y_nm"])] for r in rows])
    # and its increments between frames: 0.089 nm RMS before, 0.024 nm after
    t_mid = np.array([session.frame(k).t_mid_s for k in range(len(session))])
    p_true = np.column_stack([np.interp(t_mid, tt, tv[:, 0]), np.interp(t_mid, tt, tv[:, 1])])
    p_true += 0.5 * (np.array([sign[k] for k in range(len(session))]) - sign[0])[:, None] * bias
    increments = np.diff(xy, axis=0) - np.diff(p_true, axis=0)
    assert np.sqrt(np.mean(increments**2)) < 0.05
    for k in (5, 15):
        mine = samples[frame == k]
        t_mid = session.frame(k).t_mid_s
        assert xy[k, 0] == pytest.approx(np.interp(t_mid, mine[:, 0], mine[:, 1]), abs=0.05)
    assert (tmp_path / "run" / "trajectory_smoothed.csv").is_file()


WARMUP = Path(__file__).parents[2] / "config" / "scenarios" / "hidden" / "warmup.toml"


def _residual_block_shift_px(session_dir: Path) -> tuple[float, int]:
    """RMS of the valid block vectors between consecutive frames, px, and the pairs."""
    session = read_session(session_dir)
    vectors = []
    for i in range(len(session) - 1):
        r = measure_drift(
            np.asarray(session.frames[i], dtype=np.float64),
            np.asarray(session.frames[i + 1], dtype=np.float64),
            pixel_size_nm=session.meta.pixel_size_nm,
            config=RegistrationConfig(coarse=False),
            prior_px=(0.0, 0.0),
        )
        assert r.valid, r.reason
        vectors.append(np.asarray(r.field.vectors_px)[np.asarray(r.field.valid)])
    v = np.concatenate(vectors)
    return float(np.sqrt(np.mean(v**2))), len(vectors)


def test_afmdrift_correct_dewarps_frames_to_the_reference_geometry(tmp_path: Path) -> None:
    """`afmdrift correct` moves every row back by the drift at its scan time:
    consecutive corrected frames of a warm-up session line up to a small
    fraction of a pixel, block by block, where the raw frames are pixels apart."""
    session = tmp_path / "warmup"
    record_session(WARMUP, session, frames=16)
    raw_rms, _ = _residual_block_shift_px(session)
    assert main(["correct", str(session), "--out", str(tmp_path / "corrected")]) == 0
    rms, pairs = _residual_block_shift_px(tmp_path / "corrected")
    assert pairs == 15
    assert raw_rms > 0.5
    assert rms < 0.1
    assert (
        main(
            [
                "correct",
                str(session),
                "--out",
                str(tmp_path / "npy"),
                "--format",
                "npy",
                "--trajectory",
                "causal",
                "--fill",
                "nan",
            ]
        )
        == 0
    )
    stack = np.load(tmp_path / "npy" / "frames.npy")
    assert stack.shape == (16, *read_session(session).frames.shape[1:])
    assert np.isnan(stack).any()  # the part of the reference a drifted frame did not scan


def test_dewarp_refuses_samples_it_cannot_use() -> None:
    frame = read_session_frame()
    with pytest.raises(ValueError, match="one \\(x, y\\) image position per time"):
        dewarp_frame(frame, [1.0, 2.0], [[0.0, 0.0]])
    with pytest.raises(ValueError, match="finite"):
        dewarp_frame(frame, [1.0], [[np.nan, 0.0]])


def read_session_frame() -> Frame:
    return Frame(
        index=0,
        heights_nm=np.zeros((64, 64), np.float32),
        pixel_size_nm=(1.0, 1.0),
        t_start_s=0.0,
        t_end_s=16.0,
    )


def test_the_run_can_archive_dewarped_frames(creep_session: Path, tmp_path: Path) -> None:
    """`[service] archive_corrected`: every measured frame is also kept de-warped
    by its causal trajectory, in the same per-frame code the daemon runs."""
    cfg = AfmdriftConfig()
    cfg = cfg.model_copy(
        update={"service": cfg.service.model_copy(update={"archive_corrected": True})}
    )
    replay_session(creep_session, tmp_path / "run", config=cfg)
    kept = sorted((tmp_path / "run" / "corrected").glob("*.npy"))
    n = len(read_session(creep_session))
    assert [p.name for p in kept] == [f"{k:06d}.npy" for k in range(1, n)]
    image = np.load(kept[-1])
    assert image.dtype == np.float32
    assert np.isfinite(image).mean() > 0.5


def test_a_frame_scanned_across_an_offset_move_is_placed_row_by_row(tmp_path: Path) -> None:
    """Regression: a frame during whose scan the offset moved mixes rows from
    before and after the move; it was dropped (evaluate) or taken as a jump.
    Each block row now gets the commanded offset at its own scan time."""
    text = CREEP.read_text().replace("t_s = 4000.0", "t_s = 3916.0")  # mid-scan of frame 13
    scenario = tmp_path / "creep-mid.toml"
    scenario.write_text(text)
    session = tmp_path / "session"
    record_session(scenario, session, duration_s=5000.0)
    s = read_session(session)
    move = next(e for e in s.events if e.kind.value == "offset_move")
    assert s.frame_times[13, 0] < move.t_s < s.frame_times[13, 1]
    summary = replay_session(session, tmp_path / "run", config=AfmdriftConfig())
    with summary.measurements_csv.open() as fh:
        rows = list(csv.DictReader(fh))
    assert rows[13]["reason"] == ""
    assert s.truth is not None
    tt, tv = s.truth[:, 0], s.truth[:, 1:3]
    bias = np.asarray(
        json.loads((session / "session.json").read_text())["simulator"]["scan_direction_bias_nm"]
    )
    sign = np.array([1 if d.value == "up" else -1 for d in s.directions])
    t = np.array([s.frame(k).t_mid_s for k in range(len(rows))])
    true = np.column_stack([np.interp(t, tt, tv[:, 0]), np.interp(t, tt, tv[:, 1])])
    true += -true[0] + 0.5 * (sign - sign[0])[:, None] * bias
    xy = np.array([[float(r["x_nm"]), float(r["y_nm"])] for r in rows])
    increments = np.diff(xy, axis=0) - np.diff(true, axis=0)
    assert np.abs(increments[11:14]).max() < 1.0  # around the frame with the move
