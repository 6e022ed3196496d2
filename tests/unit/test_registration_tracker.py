"""DriftTracker: streaming registration, reference modes and state safety."""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmdrift.drivers import Frame
from afmdrift.registration import (
    DriftTracker,
    InvalidFrameError,
    RegistrationConfig,
    RegistrationError,
    measure_drift,
)
from afmdrift.registration._engine import BlockEngine
from afmdrift.testing import TextureShifter, add_noise, particle_texture, rough_texture

PIXEL_NM = 2.0


def _sequence(
    path: np.ndarray, *, shape: tuple[int, int], seed: int, snr: float = 10.0
) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    margin = int(np.ceil(np.abs(path).max())) + 8
    tex = particle_texture(
        (shape[0] + 2 * margin, shape[1] + 2 * margin), pixel_size_nm=PIXEL_NM, rng=rng
    )
    shifter = TextureShifter(tex)
    return [add_noise(shifter.crop(shape, dx_px=dx, dy_px=dy), snr=snr, rng=rng) for dx, dy in path]


@pytest.fixture(scope="module")
def wander() -> tuple[np.ndarray, list[np.ndarray]]:
    """80 frames of 256×256 drifting out to 90 px and back (two re-anchors)."""
    t = np.arange(80)
    path = np.column_stack([90.0 * np.sin(np.pi * t / 79.0), 30.0 * np.sin(2 * np.pi * t / 79)])
    path += np.random.default_rng(0).normal(0.0, 0.3, path.shape)
    return path, _sequence(path, shape=(256, 256), seed=1)


@pytest.mark.slow
def test_keyframe_mode_stays_bounded_and_reanchors(
    wander: tuple[np.ndarray, list[np.ndarray]],
) -> None:
    path, frames = wander
    tracker = DriftTracker(pixel_size_nm=PIXEL_NM, config=RegistrationConfig(reference="keyframe"))
    assert tracker.update(frames[0]) is None
    errors = []
    reanchors = 0
    for i, frame in enumerate(frames[1:], start=1):
        step = tracker.update(frame)
        assert step is not None
        assert step.accepted, step.measurement.reason
        reanchors += step.reanchored
        errors.append(np.subtract(step.position_px, path[i] - path[0]))
        nm = np.multiply(step.position_px, PIXEL_NM)
        np.testing.assert_allclose(step.position_nm, nm)
    err = np.abs(np.asarray(errors))
    assert reanchors >= 2
    # Bounded: errors only accumulate at re-anchoring, never per frame.
    assert err.max() < 0.15, err.max()
    # Back at the start after a wide excursion, still within a few hundredths.
    assert np.hypot(*errors[-1]) < 0.1


@pytest.mark.slow
def test_consecutive_mode_tracks_and_increments_sum_to_position(
    wander: tuple[np.ndarray, list[np.ndarray]],
) -> None:
    path, frames = wander
    tracker = DriftTracker(
        pixel_size_nm=PIXEL_NM, config=RegistrationConfig(reference="consecutive")
    )
    tracker.update(frames[0])
    total = np.zeros(2)
    for i, frame in enumerate(frames[1:40], start=1):
        step = tracker.update(frame)
        assert step is not None
        assert step.accepted
        assert step.reference_index == i - 1  # always the previous frame
        assert not step.reanchored
        inc = step.increment
        assert inc.dx_px == pytest.approx(path[i, 0] - path[i - 1, 0], abs=0.05)
        total += (inc.dx_px, inc.dy_px)
        np.testing.assert_allclose(step.position_px, total, atol=1e-9)
    assert abs(total[0] - (path[39, 0] - path[0, 0])) < 0.3


def test_keyframe_increments_are_relative_to_the_previous_frame() -> None:
    path = np.array([[0.0, 0.0], [1.5, -0.5], [3.2, -0.9], [4.1, -2.0]])
    frames = _sequence(path, shape=(256, 256), seed=3)
    tracker = DriftTracker(pixel_size_nm=(2.0, 3.0))
    tracker.update(frames[0])
    prev = np.zeros(2)
    for i in range(1, 4):
        step = tracker.update(frames[i])
        assert step is not None
        assert step.accepted
        assert step.reference_index == 0
        assert step.keyframe_index == 0
        assert step.measurement.dx_px == pytest.approx(path[i, 0], abs=0.05)
        assert step.increment.dx_px == pytest.approx(path[i, 0] - path[i - 1, 0], abs=0.05)
        assert step.increment.dy_nm == pytest.approx(3.0 * (path[i, 1] - path[i - 1, 1]), abs=0.15)
        # Field vectors of the increment are relative to the previous frame too.
        v = step.increment.field.vectors_px[step.increment.field.valid]
        assert np.median(v[:, 0]) == pytest.approx(path[i, 0] - prev[0], abs=0.05)
        assert step.increment.sigma_nm >= step.measurement.sigma_nm * 0.999
        prev = path[i]


def test_invalid_input_leaves_the_tracker_unchanged() -> None:
    path = np.array([[0.0, 0.0], [2.0, 1.0], [4.0, 2.0]])
    frames = _sequence(path, shape=(128, 128), seed=4)
    tracker = DriftTracker(pixel_size_nm=PIXEL_NM)
    tracker.update(frames[0])
    first = tracker.update(frames[1])
    assert first is not None
    before = (tracker.frames_seen, tracker.position_px)
    bad = frames[2].copy()
    bad[10, 10] = np.nan
    with pytest.raises(InvalidFrameError, match="NaN"):
        tracker.update(bad)
    with pytest.raises(RegistrationError, match="shape"):
        tracker.update(frames[2][:100, :])
    with pytest.raises(InvalidFrameError, match="constant"):
        tracker.update(np.zeros((128, 128)))
    assert (tracker.frames_seen, tracker.position_px) == before
    step = tracker.update(frames[2])
    assert step is not None
    assert step.accepted
    assert step.frame_index == 2
    assert step.position_px[0] == pytest.approx(4.0, abs=0.05)


@pytest.mark.parametrize("threads", [1, 2])
def test_bad_pixels_anywhere_in_a_512_frame_are_refused_while_the_worker_measures(
    threads: int,
) -> None:
    """On two threads the calling thread computes the gradient's upper rows
    while a worker computes the lower ones (BlockEngine._split_gradient,
    at row 256): a bad pixel above or below that split, or a blank frame,
    must be refused with the tracker unchanged and the next frame measured
    right."""
    path = np.array([[0.0, 0.0], [1.5, 0.5], [3.0, 1.0], [4.5, 1.5]])
    frames = _sequence(path, shape=(512, 512), seed=8)
    tracker = DriftTracker(pixel_size_nm=PIXEL_NM, config=RegistrationConfig(threads=threads))
    tracker.update(frames[0])
    first = tracker.update(frames[1])
    assert first is not None
    assert first.accepted
    before = (tracker.frames_seen, tracker.position_px)
    for row, col, value in [
        (3, 7, np.nan),
        (500, 300, np.inf),
        (255, 0, -np.inf),
        (256, 5, np.nan),
    ]:
        bad = frames[2].copy()
        bad[row, col] = value
        with pytest.raises(InvalidFrameError, match=rf"1 NaN/Inf pixel.*row {row}, col {col}"):
            tracker.update(bad)
    with pytest.raises(InvalidFrameError, match="constant"):
        tracker.update(np.full((512, 512), 4.0))
    blank = np.zeros((512, 512))
    blank[400:410, 100] = 1.0
    with pytest.raises(InvalidFrameError, match="nearly blank"):
        tracker.update(blank)
    assert (tracker.frames_seen, tracker.position_px) == before
    for i in (2, 3):
        step = tracker.update(frames[i])
        assert step is not None
        assert step.accepted
        assert step.position_px[0] == pytest.approx(path[i, 0], abs=0.05)
        assert step.position_px[1] == pytest.approx(path[i, 1], abs=0.05)


def test_an_invalid_measurement_does_not_break_the_reference_chain() -> None:
    """A frame of unrelated content is reported invalid; the tracker keeps its
    reference and prediction, and the next good frame is measured correctly."""
    path = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 1.0], [3.0, 1.5]])
    frames = _sequence(path, shape=(256, 256), seed=5)
    tracker = DriftTracker(pixel_size_nm=PIXEL_NM)
    tracker.update(frames[0])
    tracker.update(frames[1])
    junk = rough_texture((256, 256), pixel_size_nm=PIXEL_NM, rng=np.random.default_rng(9))
    step = tracker.update(junk)
    assert step is not None
    assert not step.accepted
    assert not step.increment.valid
    assert step.increment.reason
    assert step.position_px[0] == pytest.approx(1.0, abs=0.05)  # unchanged
    step = tracker.update(frames[3])
    assert step is not None
    assert step.accepted
    assert step.reference_index == 0
    assert step.position_px[0] == pytest.approx(3.0, abs=0.05)
    assert step.increment.dx_px == pytest.approx(2.0, abs=0.05)  # since frame 1


def test_frames_are_checked_for_the_pixel_size() -> None:
    path = np.array([[0.0, 0.0], [1.0, 1.0]])
    frames = _sequence(path, shape=(128, 128), seed=6)
    tracker = DriftTracker(pixel_size_nm=(2.0, 2.0))

    def frame(i: int, pixel: tuple[float, float]) -> Frame:
        return Frame(index=i, heights_nm=frames[i], pixel_size_nm=pixel, t_start_s=0.0, t_end_s=1.0)

    assert tracker.update(frame(0, (2.0, 2.0))) is None
    with pytest.raises(RegistrationError, match="pixel size"):
        tracker.update(frame(1, (2.0, 2.5)))
    step = tracker.update(frame(1, (2.0, 2.0)))
    assert step is not None
    assert step.accepted


def test_reset_starts_over_with_a_new_reference() -> None:
    path = np.array([[0.0, 0.0], [3.0, 0.0], [6.0, 0.0]])
    frames = _sequence(path, shape=(128, 128), seed=7)
    tracker = DriftTracker(pixel_size_nm=PIXEL_NM)
    tracker.update(frames[0])
    tracker.update(frames[1])
    tracker.reset()
    assert tracker.frames_seen == 0
    assert tracker.position_px == (0.0, 0.0)
    assert tracker.update(frames[1]) is None
    step = tracker.update(frames[2])
    assert step is not None
    assert step.position_px[0] == pytest.approx(3.0, abs=0.05)
    # A different frame shape is fine after reset.
    tracker.reset()
    assert tracker.update(frames[0][:100, :120]) is None


def test_tracker_rejects_bad_pixel_size() -> None:
    with pytest.raises(RegistrationError, match="pixel_size_nm"):
        DriftTracker(pixel_size_nm=-2.0)
    with pytest.raises(RegistrationError, match="pixel_size_nm"):
        DriftTracker(pixel_size_nm=(1.0, math.nan))


@pytest.mark.parametrize(
    ("reference", "gradient"),
    [("keyframe", "x"), ("consecutive", "x"), ("keyframe", "levelled"), ("keyframe", "y")],
)
def test_results_are_bit_for_bit_independent_of_the_thread_count(
    reference: str, gradient: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Guards against the thread count (or which thread takes which batch of
    blocks) leaking into the numbers: 512×640 frames hold 80 blocks in twelve
    batches of two sizes, and 1, 2 and 3 threads must give identical block fields and
    positions, for the tracker and for measure_drift. With a pre-filter other
    than the compiled x gradient, the whole gradient image comes before any
    worker starts (a worker once measured the first batch on the previous
    frame's gradient). Two threads run twice: with a CPU each (the worker
    waits for the gate spinning) and as if on one CPU (it waits in Python)."""
    from afmdrift.registration import _passes

    t = np.arange(10)
    path = np.column_stack([2.5 * t, 1.0 * np.sin(t)])
    frames = _sequence(path, shape=(512, 640), seed=3)
    assert BlockEngine((512, 640), RegistrationConfig(gradient=gradient)).n_batches == 12
    runs = []
    for threads, cpus in ((1, 4), (2, 4), (3, 4), (2, 1)):
        monkeypatch.setattr(_passes, "available_cores", lambda cpus=cpus: cpus)
        cfg = RegistrationConfig(threads=threads, reference=reference, gradient=gradient)
        tracker = DriftTracker(pixel_size_nm=2.0, config=cfg)
        out: list[object] = []
        for frame in frames:
            step = tracker.update(frame)
            if step is not None:
                f = step.measurement.field
                out.append((step.position_px, f.vectors_px.tobytes(), f.valid.tobytes()))
        pair = measure_drift(frames[0], frames[9], pixel_size_nm=2.0, config=cfg)
        assert pair.valid, pair.reason
        out.append((pair.dx_px, pair.dy_px, pair.field.vectors_px.tobytes()))
        runs.append(out)
    assert runs[0] == runs[1] == runs[2] == runs[3]


def test_forked_child_can_measure_after_the_parent_started_its_worker_pool() -> None:
    """Regression guard: a child forked after the parent's worker threads
    started must not inherit the pool (its work would never run: a hang)."""
    import os
    import signal

    t = np.arange(3)
    frames = _sequence(np.column_stack([1.5 * t, 0.5 * t]), shape=(512, 512), seed=4)
    cfg = RegistrationConfig(threads=2)
    parent = measure_drift(frames[0], frames[2], pixel_size_nm=2.0, config=cfg)
    assert parent.valid, parent.reason
    pid = os.fork()
    if pid == 0:  # child: exit code 0 only if the same result comes out
        signal.alarm(60)  # a hang (the failure guarded against) kills the child
        try:
            child = measure_drift(frames[0], frames[2], pixel_size_nm=2.0, config=cfg)
            os._exit(0 if child.dx_px == parent.dx_px else 1)
        finally:
            os._exit(2)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, "child failed or hung (SIGALRM = -14)"


def test_gradient_rows_that_a_busy_worker_has_not_begun_are_done_by_the_caller() -> None:
    """On two threads a worker computes the lower rows of a new frame's
    gradient image (BlockEngine._split_gradient); whichever thread comes
    first does them, once, so a worker busy with another pass never holds
    the calling thread up."""
    from afmdrift.registration._blocks import gradient_and_stats
    from afmdrift.registration._passes import GradientTail

    heights = np.random.default_rng(3).standard_normal((64, 40))
    heights[50, 7] = np.nan
    grad = np.full((64, 39), 7.0, dtype=np.float32)
    tail = GradientTail(heights, 32)
    tail.run(grad)  # the calling thread, first
    want_grad, want = gradient_and_stats(heights[32:], "x")
    np.testing.assert_array_equal(grad[32:], want_grad)
    assert np.all(grad[:32] == 7.0)
    grad[32:] = 7.0
    tail.run(grad)  # the worker, late: nothing left to do
    assert np.all(grad[32:] == 7.0)
    assert tail.result() == want
    assert not want.finite
