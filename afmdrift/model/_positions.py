"""From measured image positions to drift positions p(t).

The registration engine measures where the image content of each frame sits
relative to a reference frame. Two things move image content: drift, and the
XY scan offset that the operator (or afmdrift itself) commands. Models want
drift only, so commanded moves are added back: :func:`commanded_offset_nm`
gives O(t), which the position component of the pipeline
(``afmdrift.pipeline.DriftPositions``) applies per block row; the sign
convention is stated once, here.

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

The drift trajectory (``afmdrift.model._trajectory``) goes further and
places each block row at its own scan time in both frames, which removes the
raster-timing bias of a measurement against a reference whose content sat
in other rows, and handles frames scanned across an offset move row by row.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from afmdrift.model._base import events_of_kind
from afmdrift.records import Event, EventKind, Frame

__all__ = [
    "commanded_offset_nm",
    "drift_from_measurements",
    "offset_change_nm",
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
    mt, steps = events_of_kind(events, EventKind.OFFSET_MOVE)
    if not mt.size:
        return np.zeros((t.size, 2))
    cum = np.vstack([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
    k = np.searchsorted(mt, t, side="right")
    return np.asarray(cum[k], dtype=np.float64)


def offset_change_nm(
    t_s: npt.ArrayLike, t_ref_s: npt.ArrayLike, events: Sequence[Event]
) -> npt.NDArray[np.float64]:
    """O(t) − O(t_ref): the commanded offset moved between ``t_ref_s`` and
    ``t_s`` (element by element; either may be a scalar), shape (n, 2), nm.

    The one conversion between image positions and drift positions:
    p(t) − p(t_ref) = m(t) − m(t_ref) + (O(t) − O(t_ref)).
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    ref = np.atleast_1d(np.asarray(t_ref_s, dtype=np.float64))
    if not events:  # nothing moved (a stack or movie without a log)
        return np.zeros((np.broadcast_shapes(t.shape, ref.shape)[0], 2))
    t, ref = np.broadcast_arrays(t, ref)
    # One pass over the event log for both sets of times.
    both = commanded_offset_nm(np.concatenate([t, ref]), events)
    return both[: t.size] - both[t.size :]


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
    return np.asarray(m + offset_change_nm(t, ref, events), dtype=np.float64)


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
