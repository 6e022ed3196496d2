"""The drift trajectory estimator (afmdrift.model.DriftTrajectory)."""

from __future__ import annotations

import numpy as np
import pytest

from afmdrift.model import BandConstraint, DriftTrajectory, FrameTrajectory

ROWS = 8
SCAN_S = 128.0
PERIOD_S = 256.0


def _drift(t: np.ndarray) -> np.ndarray:
    """A warm-up-like drift: fast at first, slowing down, plus a slow cycle."""
    x = 40.0 * (1 - np.exp(-t / 1500.0)) + 2.0 * np.sin(2 * np.pi * t / 900.0)
    y = -25.0 * (1 - np.exp(-t / 1200.0)) + 1.5 * np.cos(2 * np.pi * t / 700.0)
    return np.column_stack([x, y])


def _knots(k: int) -> np.ndarray:
    return k * PERIOD_S + (np.arange(ROWS) + 0.5) * SCAN_S / ROWS


def _run(
    n: int, *, keyframe_every: int, noise_nm: float, seed: int = 0
) -> tuple[DriftTrajectory, list[FrameTrajectory]]:
    """Frames measured against keyframes: the trajectory and each frame's
    causal estimate."""
    rng = np.random.default_rng(seed)
    traj = DriftTrajectory(q_nm2_s3=1e-4, window=16)
    causal = []
    for k in range(n):
        t = _knots(k)
        constraints = []
        if k > 0:
            ref = (k - 1) // keyframe_every * keyframe_every
            t_ref = _knots(ref)
            true = _drift(t) - _drift(t_ref)
            for j in range(ROWS):
                v = true[j] + rng.normal(0, noise_nm, 2)
                constraints.append(
                    BandConstraint(
                        ref, float(t[j]), float(t_ref[j]), (float(v[0]), float(v[1])), noise_nm
                    )
                )
        causal.append(
            traj.add_frame(k, t, sign=1, t_mid_s=float(t.mean()), constraints=constraints)
        )
    return traj, causal


def test_causal_trajectory_follows_a_drift_that_changes_within_each_frame() -> None:
    """Eight samples a frame, each within a fraction of a nm of the true p(t)
    (relative to the first frame's mid-scan time), using only past frames."""
    _, causal = _run(40, keyframe_every=3, noise_nm=0.05, seed=1)
    origin = _drift(np.array([_knots(0).mean()]))[0]
    errors = []
    for k, est in enumerate(causal[2:], start=2):
        assert est.t_s.size == ROWS
        errors.append(est.xy_nm - (_drift(_knots(k)) - origin))
    e = np.concatenate(errors)
    assert np.sqrt(np.mean(e**2)) < 0.5
    # within one frame the drift moved by several nm: one shift per frame
    # could not have matched all eight samples
    spread = np.ptp(_drift(_knots(1)), axis=0)
    assert spread.max() > 2.0


def test_smoothed_trajectory_is_at_least_as_good_and_leaves_the_causal_state() -> None:
    traj, _ = _run(30, keyframe_every=4, noise_nm=0.1)
    origin = _drift(np.array([_knots(0).mean()]))[0]
    before = {k: traj.estimate(k).xy_nm.copy() for k in traj.order}
    smooth = traj.smoothed()
    err_s = np.concatenate([smooth[k].xy_nm - (_drift(_knots(k)) - origin) for k in range(30)])
    assert np.sqrt(np.mean(err_s**2)) < 0.3
    for k in traj.order:  # the causal estimates are unchanged
        np.testing.assert_array_equal(traj.estimate(k).xy_nm, before[k])


def test_scan_direction_bias_is_estimated_not_bent_into_the_curve() -> None:
    """Alternating up/down frames whose images differ by a constant bias b:
    the bias is found, and the reported samples carry it (as registration
    sees it) while the curve underneath stays smooth."""
    b = np.array([3.0, 2.0])
    rng = np.random.default_rng(3)
    traj = DriftTrajectory(q_nm2_s3=1e-4, window=16)
    signs = [1 if k % 2 == 0 else -1 for k in range(30)]
    for k in range(30):
        t = _knots(k)
        constraints = []
        if k > 0:
            ref = k - 1
            t_ref = _knots(ref)
            true = _drift(t) - _drift(t_ref) + 0.5 * (signs[k] - signs[ref]) * b
            for j in range(ROWS):
                v = true[j] + rng.normal(0, 0.05, 2)
                constraints.append(
                    BandConstraint(
                        ref, float(t[j]), float(t_ref[j]), (float(v[0]), float(v[1])), 0.05
                    )
                )
        traj.add_frame(k, t, sign=signs[k], t_mid_s=float(t.mean()), constraints=constraints)
    np.testing.assert_allclose(traj.bias, b, atol=0.3)


def test_bad_input_is_refused_with_the_reason() -> None:
    traj = DriftTrajectory(q_nm2_s3=1e-4)
    traj.add_frame(0, _knots(0), sign=1, t_mid_s=64.0, constraints=[])
    with pytest.raises(ValueError, match="reference frame 7 is not in the trajectory"):
        traj.add_frame(
            1,
            _knots(1),
            sign=1,
            t_mid_s=320.0,
            constraints=[BandConstraint(7, 260.0, 10.0, (0.0, 0.0), 0.1)],
        )
    with pytest.raises(ValueError, match="start before the previous frame"):
        traj.add_frame(2, _knots(0), sign=1, t_mid_s=64.0, constraints=[])
    with pytest.raises(ValueError, match="q_nm2_s3"):
        DriftTrajectory(q_nm2_s3=0.0)


def test_a_logged_jump_is_followed_not_smoothed_over() -> None:
    """Regression: a tip change shifts the image by nanometres at once; the
    smoothness prior spread it over the frames around it (1.8 nm errors of
    the increments on gold-manipulation-8h). A break lets p jump there."""
    jump_t = _knots(10)[3] + 1.0
    step = np.array([12.0, -9.0])

    def drift(t: np.ndarray) -> np.ndarray:
        return _drift(t) + (t[:, None] >= jump_t) * step

    errors = {}
    for with_break in (False, True):
        traj = DriftTrajectory(q_nm2_s3=1e-4)
        if with_break:
            traj.add_break(jump_t)
        rng = np.random.default_rng(5)
        origin = drift(np.array([_knots(0).mean()]))[0]
        worst = 0.0
        for k in range(20):
            t = _knots(k)
            constraints = []
            if k > 0:
                t_ref = _knots(0)
                true = drift(t) - drift(t_ref)
                for j in range(ROWS):
                    v = true[j] + rng.normal(0, 0.05, 2)
                    constraints.append(
                        BandConstraint(0, float(t[j]), float(t_ref[j]), (v[0], v[1]), 0.05)
                    )
            est = traj.add_frame(k, t, sign=1, t_mid_s=float(t.mean()), constraints=constraints)
            if k >= 2:
                worst = max(worst, float(np.abs(est.xy_nm - (drift(t) - origin)).max()))
        errors[with_break] = worst
    assert errors[True] < 0.25 < 0.5 < errors[False]


def test_without_history_memory_is_bounded_and_estimates_are_the_same() -> None:
    """The daemon's trajectory (keep_history=False) forgets marginalised
    frames, so it does not grow with the run, and gives the same causal
    estimates as one that keeps everything for its smoothed estimate."""
    rng = np.random.default_rng(9)
    full = DriftTrajectory(q_nm2_s3=1e-4)
    lean = DriftTrajectory(q_nm2_s3=1e-4, keep_history=False)
    for k in range(120):
        t = _knots(k)
        constraints = []
        if k > 0:
            ref = (k - 1) // 3 * 3
            t_ref = _knots(ref)
            true = _drift(t) - _drift(t_ref)
            for j in range(ROWS):
                v = true[j] + rng.normal(0, 0.05, 2)
                constraints.append(
                    BandConstraint(ref, float(t[j]), float(t_ref[j]), (v[0], v[1]), 0.05)
                )
        a = full.add_frame(k, t, sign=1, t_mid_s=float(t.mean()), constraints=constraints)
        b = lean.add_frame(k, t, sign=1, t_mid_s=float(t.mean()), constraints=constraints)
        np.testing.assert_allclose(b.xy_nm, a.xy_nm, atol=1e-9)
    assert len(full.frames) == 120
    assert len(lean.frames) <= lean.window + 3
    with pytest.raises(ValueError, match="keep_history=False"):
        lean.smoothed()


def test_a_down_frames_uncertainty_is_that_of_its_reported_position_not_of_p_alone() -> None:
    """Regression: with alternating scan directions a down frame's p alone is
    known only up to the scan-direction bias (prior 10 nm), and its reported
    σ was that of p alone (several nm) although the reported p + bias was
    within 0.2 nm; fed to the model as a weight, it made down frames count
    ~100× less than up frames."""
    rng = np.random.default_rng(3)
    bias = np.array([3.0, 2.0])
    noise = 0.05
    traj = DriftTrajectory(q_nm2_s3=1e-4, window=4)
    origin = _drift(np.array([_knots(0).mean()]))[0]
    causal = []
    for k in range(12):
        t = _knots(k)
        sign = 1 if k % 2 == 0 else -1
        constraints = []
        if k > 0:
            ref = k - 1
            t_ref = _knots(ref)
            ds = 0.5 * (sign - (1 if ref % 2 == 0 else -1))
            true = _drift(t) - _drift(t_ref) + ds * bias
            for j in range(ROWS):
                v = true[j] + rng.normal(0, noise, 2)
                constraints.append(
                    BandConstraint(
                        ref, float(t[j]), float(t_ref[j]), (float(v[0]), float(v[1])), noise
                    )
                )
        est = traj.add_frame(k, t, sign=sign, t_mid_s=float(t.mean()), constraints=constraints)
        causal.append((sign, est))
    for k, (sign, est) in enumerate(causal[1:], start=1):
        reported_true = _drift(_knots(k)) - origin + 0.5 * (sign - 1) * bias
        # the σ describes the reported value's error, and is not the bias prior's
        assert np.all(np.abs(est.xy_nm - reported_true) < 4.0 * est.sigma_nm), (k, sign)
        if k >= 3 and sign < 0:
            # as well known as the up frame before it (frames 0-2 alone leave
            # the bias and the curve's bend confounded)
            assert est.mid_sigma_nm < 2.0 * causal[k - 1][1].mid_sigma_nm, (k, est.mid_sigma_nm)
    smooth = traj.smoothed()
    mids = [smooth[k].mid_sigma_nm for k in range(2, 12)]
    assert max(mids) < 2.0 * min(mids)


def _keyframe_constraints(k: int, ref: int, noise_nm: np.ndarray) -> list[BandConstraint]:
    """Frame ``k``'s block rows measured against frame ``ref``, with the
    given noise (ROWS, 2)."""
    t, t_ref = _knots(k), _knots(ref)
    v = _drift(t) - _drift(t_ref) + noise_nm
    return [
        BandConstraint(ref, float(t[j]), float(t_ref[j]), (float(v[j, 0]), float(v[j, 1])), 0.05)
        for j in range(ROWS)
    ]


def test_a_new_reference_is_held_where_it_was_estimated_and_its_sigma_carried() -> None:
    """Regression (issue 42): a new reference without a measurement of its
    own was added with free knots, so every later frame measured against it
    re-estimated it, and the positions of its chain fell behind their
    measured displacements from it. Now its estimate is held (to numerical
    precision), the frames of its chain are that estimate plus their
    displacement from it (as a trajectory that starts at it finds), and
    their σ is the root-sum-square of the two."""
    noise = np.random.default_rng(11).normal(0, 0.05, (30, ROWS, 2))
    traj = DriftTrajectory(q_nm2_s3=1e-4, window=8, keep_history=False)
    alone = DriftTrajectory(q_nm2_s3=1e-4, window=8, keep_history=False)
    traj.add_frame(0, _knots(0), sign=1, t_mid_s=float(_knots(0).mean()), constraints=[])
    for k in range(1, 6):
        t = _knots(k)
        constraints = _keyframe_constraints(k, 0, noise[k])
        traj.add_frame(k, t, sign=1, t_mid_s=float(t.mean()), constraints=constraints)
    ref = traj.add_reference(6, _knots(6), sign=1, t_mid_s=float(_knots(6).mean()))
    alone.add_frame(6, _knots(6), sign=1, t_mid_s=float(_knots(6).mean()), constraints=[])
    assert ref.mid_sigma_nm > 0.1  # an estimate, carried across a frame period
    for k in range(7, 30):
        t = _knots(k)
        constraints = _keyframe_constraints(k, 6 if k < 18 else 17, noise[k])
        est = traj.add_frame(k, t, sign=1, t_mid_s=float(t.mean()), constraints=constraints)
        own = alone.add_frame(k, t, sign=1, t_mid_s=float(t.mean()), constraints=constraints)
        if 6 in traj.frames:
            np.testing.assert_allclose(traj.estimate(6).mid_nm, ref.mid_nm, atol=1e-6)
        # the reference's estimate plus the displacement from it
        np.testing.assert_allclose(est.mid_nm - ref.mid_nm, own.mid_nm, atol=1e-4)
        # σ: the estimate's and the displacement's, in root-sum-square
        relative = np.sqrt(est.mid_sigma_nm**2 - ref.mid_sigma_nm**2)
        assert relative == pytest.approx(own.mid_sigma_nm, rel=0.1)
