"""From measured image positions to drift positions p(t).

The registration engine measures where the image content of each frame sits
relative to a reference frame. Two things move image content: drift, and the
XY scan offset that the operator (or afmdrift itself) commands. Models want
drift only, so commanded moves are added back here. The service and
``afmdrift evaluate`` both use :func:`drift_from_measurements`, so there is one
definition of the sign convention.

Sign convention
---------------
Registration convention: a feature at image position u in the reference
appears at u + m in the current frame (m is the *measured image position*).
Drift p moves the sample under the tip by +p, so it moves image content by
+p. A commanded offset move of +Δ moves the scan window by +Δ over the sample,
so it moves image content by −Δ. With O(t) the cumulative commanded offset
(sum of ``offset_move`` deltas logged at or before t)::

    m(t) = p(t) − (O(t) − O(t_ref))      ⇒      p(t) = m(t) + O(t) − O(t_ref)

where t_ref is the time of the reference frame (frame 0), so p(t_ref) = 0.

Why mid-scan time
-----------------
A frame's rows are scanned at different times. The block-averaged displacement
of a frame against the reference is, to first order, the mean over its rows of
the drift at each row's scan time. For linear drift p(t) = a + b·t the mean of
p over equally spaced row times is p at their mean, which is the mid-scan time
``Frame.t_mid_s``. Each measurement is therefore placed at ``t_mid_s``.
Where the drift curves within a frame (creep, warm-up) this is only first-order
accurate; the comparison against simulator truth uses the exact per-line form
(:func:`truth_frame_mean`, the mean of p over the row times) instead.

Per-line timing matters a second time when drift moves content by many rows
per frame: the reference frame scanned that content at other rows, hence at
other times, than the ones its mid-scan time stands for.
:func:`correct_slow_axis_timing` removes that first-order bias (a few percent
of each increment at 30 px per frame).

A frame during whose scan an offset move happened is displaced by different
amounts above and below the move; :func:`frames_spanning_moves` finds them so
they are not used as drift observations.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from afmdrift.records import Event, EventKind, Frame

__all__ = [
    "commanded_offset_nm",
    "correct_slow_axis_timing",
    "drift_from_measurements",
    "frames_spanning_moves",
    "truth_frame_mean",
]


def commanded_offset_nm(t_s: npt.ArrayLike, events: Sequence[Event]) -> npt.NDArray[np.float64]:
    """Cumulative commanded XY offset O(t) from ``offset_move`` events.

    Parameters
    ----------
    t_s : array_like, shape (n,)
        Query times, s.
    events : sequence of Event
        The event log; only ``offset_move`` entries are used, each adding its
        ``(x_nm, y_nm)`` at its time ``t_s`` (a move at exactly t counts at t).

    Returns
    -------
    ndarray, shape (n, 2)
        O(t) in nm, zero before the first move.
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    moves = [e for e in events if e.kind is EventKind.OFFSET_MOVE]
    if not moves:
        return np.zeros((t.size, 2))
    mt = np.array([e.t_s for e in moves], dtype=np.float64)
    order = np.argsort(mt, kind="stable")
    mt = mt[order]
    cum = np.cumsum(np.array([[e.x_nm, e.y_nm] for e in moves], dtype=np.float64)[order], axis=0)
    cum = np.vstack([np.zeros((1, 2)), cum])
    k = np.searchsorted(mt, t, side="right")
    return np.asarray(cum[k], dtype=np.float64)


def drift_from_measurements(
    t_s: npt.ArrayLike,
    image_position_nm: npt.ArrayLike,
    events: Sequence[Event],
    *,
    t_ref_s: float | None = None,
) -> npt.NDArray[np.float64]:
    """Drift positions p from measured image positions, removing commanded moves.

    Parameters
    ----------
    t_s : array_like, shape (n,)
        Time of each measurement (the frame's mid-scan time), s.
    image_position_nm : array_like, shape (n, 2)
        Measured cumulative image position m (x, y) of each frame relative to
        the reference frame (``TrackStep.position_nm``), nm.
    events : sequence of Event
        Event log; ``offset_move`` entries are the commanded moves, including
        afmdrift's own corrections.
    t_ref_s : float, optional
        Time of the reference frame (default: ``t_s[0]``).

    Returns
    -------
    ndarray, shape (n, 2)
        p = m + O(t) − O(t_ref), nm.

    Raises
    ------
    ValueError
        If the shapes disagree.
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    m = np.asarray(image_position_nm, dtype=np.float64).reshape(-1, 2)
    if m.shape[0] != t.size:
        raise ValueError(
            f"image_position_nm has {m.shape[0]} rows for {t.size} times; need one per time"
        )
    if t.size == 0:
        return m.copy()
    ref = float(t[0]) if t_ref_s is None else float(t_ref_s)
    offset = commanded_offset_nm(t, events) - commanded_offset_nm([ref], events)[0]
    return np.asarray(m + offset, dtype=np.float64)


def truth_frame_mean(
    frame: Frame,
    truth_t_s: npt.ArrayLike,
    truth_nm: npt.ArrayLike,
) -> npt.NDArray[np.float64]:
    """Mean of the true drift over a frame's row times, shape (2,).

    This is what an ideal block-averaged measurement of the frame sees
    (see the module docstring), exactly, for any drift curve.

    Parameters
    ----------
    frame : Frame
        The frame (its timing and direction give the row times).
    truth_t_s : array_like, shape (m,)
        Times of the true drift samples, increasing, s.
    truth_nm : array_like, shape (m, 2)
        True drift p (x, y), nm.
    """
    tt = np.asarray(truth_t_s, dtype=np.float64)
    tv = np.asarray(truth_nm, dtype=np.float64).reshape(-1, 2)
    rows = frame.row_times_s()
    x = np.interp(rows, tt, tv[:, 0]).mean()
    y = np.interp(rows, tt, tv[:, 1]).mean()
    return np.array([x, y])


def correct_slow_axis_timing(
    t_s: npt.ArrayLike,
    drift_nm: npt.ArrayLike,
    image_position_nm: npt.ArrayLike,
    reference_index: Sequence[int],
    row_slope_s: npt.ArrayLike,
    *,
    pixel_size_y_nm: float,
) -> npt.NDArray[np.float64]:
    """Remove the raster-timing bias of each measurement against its reference.

    A block at row r of the current frame holds content that the reference
    frame scanned at row r − d_y/Δy (d_y the measured image shift along y), at
    time t_ref(r) − s·d_y/Δy, where s is the reference's row-time slope (+line
    time for an up frame, −line time for a down frame). The measurement
    therefore compares p at the current mid-scan time with p at the reference's
    mid-scan time shifted by −s·d_y/Δy; to first order::

        p(t_cur) − p(t_ref) = d − v_ref · s · d_y / Δy

    with v_ref the drift velocity at the reference. With 30 px of drift per
    frame on a 0.25 s line this is a 3 % error of every increment, which
    accumulates along a keyframe chain; the correction is chained the same way
    (each frame inherits its reference's correction).

    Parameters
    ----------
    t_s : array_like, shape (n,)
        Mid-scan times, s.
    drift_nm : array_like, shape (n, 2)
        Uncorrected drift positions (:func:`drift_from_measurements`), NaN
        where a frame was not measured; also used for v_ref (central
        differences over the neighbouring measured frames).
    image_position_nm : array_like, shape (n, 2)
        Measured image positions m (the shifts d are m_i − m_ref).
    reference_index : sequence of int, length n
        Frame each measurement was made against (−1 or i itself: none).
    row_slope_s : array_like, shape (n,)
        d(row time)/d(row index) of each frame: +line time (up), −line time (down).
    pixel_size_y_nm : float
        Δy, nm.

    Returns
    -------
    ndarray, shape (n, 2)
        Corrected drift positions.
    """
    t = np.asarray(t_s, dtype=np.float64)
    p = np.asarray(drift_nm, dtype=np.float64).reshape(-1, 2)
    m = np.asarray(image_position_nm, dtype=np.float64).reshape(-1, 2)
    slope = np.asarray(row_slope_s, dtype=np.float64)
    n = t.size
    if not (p.shape[0] == m.shape[0] == slope.size == len(reference_index) == n):
        raise ValueError(
            f"correct_slow_axis_timing: {n} times, {p.shape[0]} drift rows, {m.shape[0]} "
            f"image rows, {slope.size} slopes, {len(reference_index)} reference indices"
        )
    ok = np.all(np.isfinite(p), axis=1)
    good = np.nonzero(ok)[0]
    corr = np.zeros((n, 2))
    # Two passes: the second takes v_ref from the corrected positions, which
    # removes the second-order error of the first (v from biased positions).
    for _ in range(2):
        q = p + corr
        v = np.zeros((n, 2))
        for k in range(good.size):
            lo = good[max(k - 1, 0)]
            hi = good[min(k + 1, good.size - 1)]
            if hi != lo:
                v[good[k]] = (q[hi] - q[lo]) / (t[hi] - t[lo])
        corr = np.zeros((n, 2))
        for i in range(n):
            r = int(reference_index[i])
            if not ok[i] or r < 0 or r >= i or not ok[r]:
                continue
            corr[i] = corr[r] - v[r] * slope[r] * (m[i, 1] - m[r, 1]) / pixel_size_y_nm
    return np.asarray(p + corr, dtype=np.float64)


def frames_spanning_moves(
    frame_times_s: npt.ArrayLike, events: Sequence[Event]
) -> npt.NDArray[np.bool_]:
    """Frames during whose scan a commanded offset move happened, shape (n,).

    Rows scanned before the move and rows scanned after it are displaced by
    different amounts, so the frame's measurement is neither the drift before
    nor after the move; such frames must not become drift observations.

    Parameters
    ----------
    frame_times_s : array_like, shape (n, 2)
        ``(t_start_s, t_end_s)`` of each frame.
    events : sequence of Event
        The event log (``offset_move`` entries are used).
    """
    ft = np.asarray(frame_times_s, dtype=np.float64).reshape(-1, 2)
    moves = np.array([e.t_s for e in events if e.kind is EventKind.OFFSET_MOVE])
    if moves.size == 0:
        return np.zeros(ft.shape[0], dtype=bool)
    inside = (moves[None, :] > ft[:, :1]) & (moves[None, :] < ft[:, 1:2])
    return np.asarray(np.any(inside, axis=1), dtype=np.bool_)
