"""A block pass started ahead of its frame (BlockEngine.measure_ahead,
DriftTracker.measure_ahead, FramePipeline.run) gives
exactly what measuring the frame then would; the three-point sub-pixel
methods, now compiled into the pass, keep their formulas."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from afmdrift.config import AfmdriftConfig
from afmdrift.registration import DriftTracker, RegistrationConfig, TrackStep, _subpixel
from afmdrift.registration._blocks import config_for_image
from afmdrift.registration._constants import SubpixelConstants
from afmdrift.registration._engine import BlockEngine, BlockMeasurement
from afmdrift.registration._errors import InvalidFrameError
from afmdrift.registration._fftw import BatchedRealFFT
from afmdrift.registration._passes import Peaks
from afmdrift.testing import TextureShifter, add_noise, particle_texture


def _frames(n: int, *, shape: tuple[int, int] = (256, 256), seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    tex = TextureShifter(
        particle_texture((shape[0] + 60, shape[1] + 60), pixel_size_nm=2.0, rng=rng)
    )
    return [
        add_noise(tex.crop(shape, dx_px=1.7 * k, dy_px=-0.6 * k), snr=10.0, rng=rng)
        for k in range(n)
    ]


def _same(a: BlockMeasurement, b: BlockMeasurement) -> None:
    for name in ("vectors_px", "confidence", "mse", "measured", "placed", "in_overlap"):
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name
    assert a.n_measured == b.n_measured


def _same_step(a: TrackStep | None, b: TrackStep | None) -> None:
    if a is None or b is None:
        assert a is None
        assert b is None
        return
    assert a.position_px == b.position_px
    assert a.measurement.field.vectors_px.tobytes() == b.measurement.field.vectors_px.tobytes()


def _engine_and_reference(frames: list[np.ndarray]) -> tuple[BlockEngine, object]:
    cfg = config_for_image(RegistrationConfig(threads=2), frames[0])
    engine = BlockEngine(frames[0].shape, cfg)
    grad = engine.prepare(frames[0])[0]
    return engine, engine.reference(grad)


def test_a_pass_started_ahead_equals_the_pass_measured_then() -> None:
    frames = _frames(3)
    engine, ref = _engine_and_reference(frames)
    grad = np.empty(engine.layout.grad_shape, np.float32)
    plain, top, left = engine.measure(
        ref, grad, prior_px=(3.4, -1.2), heights=frames[2], check=lambda stats: None
    )
    grad2 = np.empty_like(grad)
    assert engine.measure_ahead(
        ref, grad2, prior_px=(3.4, -1.2), heights=frames[2], check=lambda stats: None
    )
    ahead, top2, left2 = engine.measure(
        ref, grad2, prior_px=(3.4, -1.2), heights=frames[2], check=lambda stats: None
    )
    _same(plain, ahead)
    assert np.array_equal(top, top2)
    assert np.array_equal(left, left2)
    assert np.array_equal(grad, grad2)
    assert engine._ahead is None


def test_finish_ahead_leaves_no_worker_running_and_keeps_the_result() -> None:
    frames = _frames(2)
    engine, ref = _engine_and_reference(frames)
    grad = np.empty(engine.layout.grad_shape, np.float32)
    assert engine.measure_ahead(
        ref, grad, prior_px=(1.7, -0.6), heights=frames[1], check=lambda stats: None
    )
    pending = engine._ahead
    assert pending is not None
    engine.finish_ahead()
    assert all(w.done() for w in pending.run.workers)
    assert int(pending.run.counter[0]) >= engine.n_batches  # every batch was taken
    kept = pending.result
    got, _, _ = engine.measure(
        ref, grad, prior_px=(1.7, -0.6), heights=frames[1], check=lambda stats: None
    )
    assert got is kept


def test_a_different_call_drops_the_pass_and_measures_afresh() -> None:
    frames = _frames(3)
    engine, ref = _engine_and_reference(frames)
    grad = np.empty(engine.layout.grad_shape, np.float32)
    assert engine.measure_ahead(
        ref, grad, prior_px=(0.0, 0.0), heights=frames[1], check=lambda stats: None
    )
    # another prior: the pass started ahead is not this one
    got, _, _ = engine.measure(
        ref, grad, prior_px=(3.4, -1.2), heights=frames[2], check=lambda stats: None
    )
    fresh_engine, fresh_ref = _engine_and_reference(frames)
    want, _, _ = fresh_engine.measure(
        fresh_ref,
        np.empty_like(grad),
        prior_px=(3.4, -1.2),
        heights=frames[2],
        check=lambda stats: None,
    )
    _same(got, want)
    # and a new reference (another use of the work arrays) drops one too
    assert engine.measure_ahead(
        ref, grad, prior_px=(1.7, -0.6), heights=frames[1], check=lambda stats: None
    )
    pending = engine._ahead
    assert pending is not None
    engine.reference(engine.prepare(frames[0])[0])
    assert engine._ahead is None
    assert all(w.done() for w in pending.run.workers)


def test_a_frame_the_check_refuses_is_not_started_and_the_update_still_refuses_it() -> None:
    frames = _frames(3)
    bad = frames[2].copy()
    bad[100, 7] = np.nan
    tracker = DriftTracker(pixel_size_nm=2.0, config=RegistrationConfig(threads=2))
    tracker.update(frames[0])
    tracker.update(frames[1])
    assert not tracker.measure_ahead(bad)
    with pytest.raises(InvalidFrameError, match=r"NaN|finite"):
        tracker.update(bad)
    # the tracker is unchanged and goes on
    step = tracker.update(frames[2])
    assert step is not None
    assert step.accepted


def test_heights_each_update_converts_anew_are_not_started_ahead() -> None:
    frames = [np.round(f * 100).astype(np.int32) for f in _frames(3)]
    tracker = DriftTracker(pixel_size_nm=2.0, config=RegistrationConfig(threads=2))
    tracker.update(frames[0])
    tracker.update(frames[1])
    assert not tracker.measure_ahead(frames[2])  # a pass on a copy no update asks for
    step = tracker.update(frames[2])
    assert step is not None
    assert step.accepted


def test_memory_mapped_frames_are_started_ahead_regression_never_overlapped(
    tmp_path: Path,
) -> None:
    """Guards against the memory-mapped stack of ``afmdrift measure
    STACK.npy`` never running a pass ahead: each call viewed an ``np.memmap``
    frame as a new plain array, so no pass was started (and none would have
    matched its update)."""
    frames = _frames(5)
    path = tmp_path / "stack.npy"
    np.save(path, np.stack(frames).astype(np.float32))
    mapped = np.load(path, mmap_mode="r")
    cfg = RegistrationConfig(threads=2)
    plain = DriftTracker(pixel_size_nm=2.0, config=cfg)
    ahead = DriftTracker(pixel_size_nm=2.0, config=cfg)
    started = fresh = 0
    for k in range(len(frames)):
        a = plain.update(np.array(mapped[k]))
        engine = ahead._engine
        pending = None if engine is None else engine._ahead
        b = ahead.update(mapped[k])
        if pending is not None:
            # the update measured the very pass started for it
            fresh += pending.result is None
        if 0 < k < len(frames) - 1:
            started += ahead.measure_ahead(mapped[k + 1])
            ahead.finish_ahead()
        _same_step(a, b)
    # every frame after the first measured one (which the coarse alignment starts)
    assert started == len(frames) - 2
    assert fresh == 0


def test_tracker_steps_are_bit_for_bit_the_same_with_passes_started_ahead() -> None:
    frames = _frames(12, shape=(300, 280), seed=2)
    cfg = RegistrationConfig(threads=2)
    plain = DriftTracker(pixel_size_nm=2.0, config=cfg)
    ahead = DriftTracker(pixel_size_nm=2.0, config=cfg)
    started = 0
    for k, frame in enumerate(frames):
        a = plain.update(frame)
        b = ahead.update(frame)
        if k + 1 < len(frames):
            started += ahead.measure_ahead(frames[k + 1])
        _same_step(a, b)
    # the first frame after the reference starts from the coarse alignment:
    # no pass is started ahead for it (nor for the reference)
    assert started == len(frames) - 2


def test_track_stack_output_is_the_same_with_and_without_lookahead(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from afmdrift.io import AfmImage
    from afmdrift.runs import track_stack

    frames = _frames(8, seed=5)
    images = [
        AfmImage(heights_nm=f, pixel_size_nm=(2.0, 2.0), path=Path("s.npy"), frame=k)
        for k, f in enumerate(frames)
    ]
    with_ahead = list(track_stack(images, AfmdriftConfig()))
    monkeypatch.setattr(DriftTracker, "measure_ahead", lambda self, *a, **k: False)
    without = list(track_stack(images, AfmdriftConfig()))
    assert with_ahead == without
    assert all(doc["valid"] for doc in with_ahead)


def _three_point_reference(cm: float, c0: float, cp: float, method: str) -> tuple[float, bool]:
    """The three-point formulas, written out independently of the kernel."""
    if method == "sinc":  # Foroosh et al. (2002)
        side = max(cp, cm)
        off = side / (side + c0) if side > 0 else 0.0
        off = off if cp >= cm else -off
    elif method == "parabolic":
        den = cm - 2 * c0 + cp
        off = 0.5 * (cm - cp) / den if den < 0 else 0.0
    else:
        lm, l0, lp = (math.log(max(v, 1e-12)) for v in (cm, c0, cp))
        den = lm - 2 * l0 + lp
        off = 0.5 * (lm - lp) / den if den < 0 else 0.0
    ok = math.isfinite(off) and abs(off) <= 1.0 and c0 > 0
    return (off if ok else 0.0), ok


@pytest.mark.parametrize("method", ["sinc", "parabolic", "gaussian"])
def test_three_point_subpixel_kernel_follows_its_formula(method: str) -> None:
    rng = np.random.default_rng(1)
    m = 4
    corr = rng.uniform(-0.2, 1.0, (40, 2 * m + 1, 2 * m + 1)).astype(np.float32)
    sy = rng.integers(-m, m + 1, 40)
    sx = rng.integers(-m, m + 1, 40)
    corr[np.arange(40), sy + m, sx + m] = 1.5  # a peak, also at the edges
    scale = 3.0
    peaks = Peaks.empty(40)
    peaks.sy[:], peaks.sx[:] = sy, sx
    fy, fx, ok = peaks.fy, peaks.fx, peaks.ok
    c = SubpixelConstants(
        method=_subpixel.SUBPIXEL_CODES[method], fy=np.zeros(1), fx=np.zeros(1),
        shift=np.array([m, m], dtype=np.intp), envelope=np.zeros(2), scale=scale,
    )  # fmt: skip
    order = rng.permutation(40).astype(np.intp)  # the batch's order of the blocks
    _subpixel.subpixel_3pt(c, order, corr[order], peaks)
    for i in range(40):
        cy, cx = sy[i] + m, sx[i] + m
        c = corr[i].astype(np.float64) / scale
        y = [c[max(cy - 1, 0), cx], c[cy, cx], c[min(cy + 1, 2 * m), cx]]
        x = [c[cy, max(cx - 1, 0)], c[cy, cx], c[cy, min(cx + 1, 2 * m)]]
        oy, ok_y = _three_point_reference(*y, method)
        ox, ok_x = _three_point_reference(*x, method)
        assert fy[i] == pytest.approx(oy, rel=1e-12, abs=1e-15)
        assert fx[i] == pytest.approx(ox, rel=1e-12, abs=1e-15)
        assert ok[i] == (ok_x and ok_y)


@pytest.mark.parametrize("method", ["sinc", "parabolic", "gaussian"])
def test_three_point_methods_measure_a_known_shift(method: str) -> None:
    from afmdrift.registration import measure_drift

    rng = np.random.default_rng(3)
    tex = TextureShifter(particle_texture((360, 360), pixel_size_nm=2.0, rng=rng))
    a = tex.crop((256, 256), dx_px=0.0, dy_px=0.0)
    b = tex.crop((256, 256), dx_px=3.3, dy_px=-1.6)
    r = measure_drift(
        a, b, pixel_size_nm=2.0, config=RegistrationConfig(subpixel=method), prior_px=(3.0, -2.0)
    )
    assert r.valid, r.reason
    assert abs(r.dx_px - 3.3) < 0.35
    assert abs(r.dy_px + 1.6) < 0.35


def test_plans_on_shared_arrays_equal_plans_on_their_own() -> None:
    big = BatchedRealFFT(6, (48, 40), planner="estimate", wisdom_path=None, out_rows=21)
    small = BatchedRealFFT(
        3, (48, 40), planner="estimate", wisdom_path=None, out_rows=21, share=big
    )
    alone = BatchedRealFFT(3, (48, 40), planner="estimate", wisdom_path=None, out_rows=21)
    assert np.shares_memory(small.real, big.real)
    x = np.random.default_rng(0).standard_normal((3, 48, 40)).astype(np.float32)
    for fft in (small, alone):
        fft.real[:] = x
        fft.forward()
        fft.inverse()
    assert np.array_equal(small.out, alone.out)
    np.testing.assert_allclose(alone.out / (48 * 40), x[:, :21], atol=1e-5)
    for n, shape in ((8, (48, 40)), (2, (64, 40)), (2, (48, 36))):
        with pytest.raises(ValueError, match="shared"):
            BatchedRealFFT(n, shape, planner="estimate", wisdom_path=None, out_rows=21, share=big)


def test_a_child_forked_while_a_pass_runs_ahead_measures_on_its_own() -> None:
    """The child has none of the parent's workers: a pass started ahead in the
    parent must not be waited for in the child (a hang)."""
    import os
    import signal

    frames = _frames(3)
    engine, ref = _engine_and_reference(frames)
    grad = np.empty(engine.layout.grad_shape, np.float32)
    want, _, _ = engine.measure(
        ref, grad, prior_px=(3.4, -1.2), heights=frames[2], check=lambda stats: None
    )
    assert engine.measure_ahead(
        ref, grad, prior_px=(1.7, -0.6), heights=frames[1], check=lambda stats: None
    )
    pid = os.fork()
    if pid == 0:  # child: exit code 0 only if the same result comes out
        signal.alarm(60)
        try:
            got, _, _ = engine.measure(
                ref, grad, prior_px=(3.4, -1.2), heights=frames[2], check=lambda stats: None
            )
            os._exit(0 if got.vectors_px.tobytes() == want.vectors_px.tobytes() else 1)
        finally:
            os._exit(2)
    engine.finish_ahead()
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, "child failed or hung (SIGALRM = -14)"
