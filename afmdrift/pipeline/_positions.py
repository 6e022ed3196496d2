"""Where each frame sits: the one streaming position component.

:class:`DriftPositions` turns frames into drift positions for the daemon,
``afmdrift replay``, ``afmdrift evaluate`` and ``afmdrift diagnose`` (all
through :class:`~afmdrift.pipeline.FramePipeline`), so every tool reports
what the daemon can do online. For each frame it

1. **places the block windows** where the content is expected: the tracker's
   own expectation (last position plus last increment) plus the image motion
   of the commanded offset moves logged since the last measured frame (a
   move of +Δ moves content by −Δ), so a re-centring move of 100 px does not
   leave the ±64 px search range;
2. **registers** the frame against the tracker's reference (keyframe policy:
   ``RegistrationConfig.reference``), with blocks judged by their residual
   from a smooth trend over the block rows (``registration._trend``);
3. **places every block row in time**: its content was scanned at
   t_cur(row + v_y) in this frame and at t_ref(row) in the reference, and the
   commanded offset O is evaluated at both times, so rows scanned before and
   after a move each get their own offset (a block row whose lines straddle a
   move, in either frame, holds content from two offsets and is left out);
4. **updates the drift trajectory** (:class:`~afmdrift.model.DriftTrajectory`,
   causal mode) with the block rows as constraints; the frame's drift
   position p is the trajectory at its mid-scan time, and its samples are
   the trajectory at its block-row times.

Positions (sign convention of ``afmdrift.model._positions``)::

    m  image position relative to the session reference (what registration sees)
    p = m + O(t) − O(t_ref)          drift position, p(t_ref) = 0

A new reference (a reset, a changed frame shape or pixel size, another
instrument) has no measurement of its own: its position is estimated, the
trajectory continued from the frames before it (the smoothness prior), so p
stays continuous; it does not feed the model. It starts a new *chain* of
positions (:meth:`DriftTrajectory.add_reference`): the estimate is held, never
re-estimated by the frames measured against it, so their p is the estimate
plus their measured displacement from it, and their σ is the root-sum-square
of the estimate's σ and the displacement's. Chains are numbered (``chain`` of
:class:`FramePosition`, on the wire): 0 for the session's first reference (or
the one a resumed service continues), then one more for each new reference.

Each scan geometry (frame shape and pixel size) keeps its own reference: a
frame of another size now and then, or a zoom in and back out, is measured
against the reference of its own geometry when there is one (its position
chain, and its chain number, go on where they stopped), and only a geometry
seen for the first time takes a new reference, with the position carried
across from the trajectory.
At most ``_GEOMETRIES_KEPT`` geometries are kept; a reset forgets them all.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from afmdrift.config import AfmdriftConfig
from afmdrift.errors import InputError
from afmdrift.model import (
    BandConstraint,
    DriftTrajectory,
    FrameTrajectory,
    default_q,
    offset_change_nm,
)
from afmdrift.pipeline._records import FrameRecord
from afmdrift.records import Event, EventKind, Frame, ScanDirection
from afmdrift.wire import FieldSummary

if TYPE_CHECKING:
    # The registration engine (pyFFTW, its plans) loads with the first tracker:
    # a tool that only reads positions (a drift log's diagnosis) never needs it.
    from afmdrift.registration import DriftResult, DriftTracker, TrackStep

__all__ = ["DriftPositions", "FramePosition", "TrackerFactory", "summarise_field"]

log = logging.getLogger(__name__)

TrackerFactory = Callable[[tuple[float, float]], "DriftTracker"]
FloatArray = npt.NDArray[np.float64]

#: Frame timings kept for the reference lookup (keyframes are rarely older).
_TIMINGS_KEPT = 256
#: Scan geometries whose reference is kept besides the current one.
_GEOMETRIES_KEPT = 4

GeometryKey = tuple[tuple[int, int], tuple[float, float]]


@dataclass(slots=True)
class _Parked:
    """The reference of a scan geometry not in use: its tracker, the image
    position m of its reference, its frame keys, its last frame's time and
    its chain number."""

    tracker: DriftTracker
    base_nm: FloatArray
    keys: dict[int, int]
    last_t_s: float | None
    chain: int
    chain_sigma_nm: float


@dataclass(slots=True)
class FramePosition:
    """Where a frame sits: image position m, drift position p, the measurement
    and the frame's trajectory samples."""

    offset: FloatArray
    reason: str
    m: FloatArray = field(default_factory=lambda: np.full(2, np.nan))
    p: FloatArray = field(default_factory=lambda: np.full(2, np.nan))
    dx: float = math.nan
    dy: float = math.nan
    sigma: float = math.nan
    valid_blocks: int = 0
    total_blocks: int = 0
    keyframe_index: int = 0
    reanchored: bool = False
    field: FieldSummary | None = None
    reference_image: npt.NDArray[np.float32] | None = None
    fed: bool = False
    trajectory: FrameTrajectory | None = None
    #: The registration's increment since the previous accepted frame, and
    #: the frame (key) the frame was measured against.
    increment: DriftResult | None = None
    reference_key: int | None = None
    #: The registration's σ of the frame's block mean against its reference,
    #: nm (``sigma`` is the trajectory's σ of p, which grows along the chain).
    measurement_sigma: float = math.nan
    #: The number of the frame's position chain (see the module docstring).
    chain: int = 0


@dataclass(frozen=True, slots=True)
class _Timing:
    t_start_s: float
    t_end_s: float
    rows: int
    direction: ScanDirection

    def times_at(self, rows_px: FloatArray) -> FloatArray:
        """Scan time of (fractional) rows, clamped to the frame: the row times
        of :func:`afmdrift.records.row_times_s` (mid-line, linear in the row)
        interpolated, computed directly."""
        r = np.minimum(np.maximum(rows_px, 0.0), self.rows - 1.0)  # (np.clip costs more)
        if self.direction is ScanDirection.DOWN:
            r = (self.rows - 1.0) - r
        line_s = (self.t_end_s - self.t_start_s) / self.rows
        return np.asarray(self.t_start_s + (r + 0.5) * line_s, dtype=np.float64)


def _sorted_unique(values: FloatArray) -> FloatArray:
    """The distinct values, sorted (``np.unique`` of a few dozen values,
    without its overhead: this runs for every frame)."""
    v = np.sort(values)
    if v.size < 2:
        return v
    keep = np.empty(v.size, dtype=bool)
    keep[0] = True
    np.not_equal(v[1:], v[:-1], out=keep[1:])
    return v[keep]


def _sign(direction: ScanDirection) -> int:
    return 1 if direction is ScanDirection.UP else -1


class DriftPositions:
    """Frames in, drift positions and trajectory samples out (see the module
    docstring). Not thread-safe: one thread at a time.

    ``keep_trajectory`` keeps every frame of the trajectory for its smoothed
    estimate (``afmdrift replay``, ``afmdrift correct``); without it, as in
    the daemon, frames no later frame can refer to are forgotten.
    ``first_prior_px`` is the user's expected drift (px) of the frames after
    the first reference until one is accepted (``--prior-px``;
    :meth:`DriftTracker.expect`).
    """

    def __init__(
        self,
        *,
        config: AfmdriftConfig,
        tracker_factory: TrackerFactory | None = None,
        keep_trajectory: bool = False,
        first_prior_px: tuple[float, float] | None = None,
    ) -> None:
        self.config = config
        # the user's expected drift of the first frame after the first reference
        self._first_prior_px = first_prior_px
        self._tracker_factory = tracker_factory or self._default_tracker_factory
        self._tracker: DriftTracker | None = None
        self._tracker_key: GeometryKey | None = None
        self._parked: dict[GeometryKey, _Parked] = {}  # other geometries' references
        self._base_nm = np.zeros(2)  # image position m of the tracker's reference
        self.t_ref_s: float | None = None  # session reference time (p = 0)
        self.last_p_nm: FloatArray | None = None
        self._reset_requested = False
        #: The current tracker's chain number, and the chains started so far.
        self.chain = 0
        self._chains = 0
        self._chain_sigma_nm = 0.0  # σ of the current chain's reference position
        q = config.model.trajectory_q
        self._q_set = q is not None
        self.trajectory = DriftTrajectory(
            q_nm2_s3=q if q is not None else default_q(math.nan),
            window=config.model.trajectory_window,
            keep_history=keep_trajectory,
        )
        # tracker frame index -> trajectory key, and the timing of those frames
        self._keys: dict[int, int] = {}
        self._timings: dict[int, _Timing] = {}
        self._last_t_s: float | None = None  # mid time of the tracker's last frame
        self._breaks_to_s = -math.inf  # tip changes up to here are breaks already
        # offset move times seen in the event log (see _moves_during)
        self._moves_of: Sequence[Event] | None = None
        self._moves_seen = 0
        self._move_times: list[float] = []

    def _default_tracker_factory(self, pixel_size_nm: tuple[float, float]) -> DriftTracker:
        from afmdrift.registration import DriftTracker

        return DriftTracker(pixel_size_nm=pixel_size_nm, config=self.config.registration)

    @property
    def reference_direction(self) -> ScanDirection | None:
        """Slow-scan direction of the session reference that positions are
        measured against (None before the first reference)."""
        sign = self.trajectory.origin_sign
        if sign is None:
            return None
        return ScanDirection.UP if sign > 0 else ScanDirection.DOWN

    def request_reset(self) -> None:
        """Make the next frame the registration reference (p stays continuous);
        the references of other scan geometries are forgotten too."""
        self._reset_requested = True
        self._parked.clear()

    # ------------------------------------------------------------------ resume

    def resume(
        self,
        *,
        t_ref_s: float | None,
        last_p_nm: FloatArray | None,
        reference: npt.NDArray[np.float32] | None,
        reference_record: FrameRecord | None,
        reference_m_nm: tuple[float, float],
    ) -> None:
        """Continue after a restart: the stored reference re-primes the tracker,
        and its recorded drift position anchors the trajectory."""
        self.t_ref_s = t_ref_s
        self.last_p_nm = last_p_nm
        if reference is None or reference_record is None:
            return
        r = reference_record
        pixel = (r.pixel_x_nm, r.pixel_y_nm)
        tracker = self._tracker_factory(pixel)
        try:
            tracker.update(reference)
        except InputError as err:
            log.warning("stored reference image unusable (%s); the next frame replaces it", err)
            return
        if not (math.isfinite(r.x_nm) and math.isfinite(r.y_nm)):
            log.warning("stored reference has no drift position; the next frame replaces it")
            return
        self._tracker = tracker
        self._tracker_key = ((reference.shape[0], reference.shape[1]), pixel)
        self._base_nm = np.array(reference_m_nm, dtype=np.float64)
        timing = _Timing(r.t_start_s, r.t_end_s, r.rows, ScanDirection(r.direction))
        knots = self._knot_times(tracker, timing, 0.0)
        self.trajectory.add_anchor(
            r.seq,
            knots,
            sign=_sign(timing.direction),
            t_mid_s=r.t_mid_s,
            p_nm=(r.x_nm, r.y_nm),
            sigma_nm=r.sigma_nm if math.isfinite(r.sigma_nm) else 0.0,
        )
        self._keys = {0: r.seq}
        self._timings = {r.seq: timing}
        self._last_t_s = r.t_mid_s
        self._chain_sigma_nm = r.sigma_nm if math.isfinite(r.sigma_nm) else 0.0

    # ------------------------------------------------------------------ a frame

    def locate(
        self,
        frame: Frame,
        *,
        seq: int,
        events: Sequence[Event],
        prediction_nm: FloatArray,
        n_fed: int,
        held: bool,
        next_frame: Frame | None = None,
    ) -> FramePosition:
        """Register ``frame`` and place it (see the module docstring).

        With ``next_frame`` (the frame the next call will be given), its
        registration starts once this frame's is done, and runs on the
        engine's workers while this frame is placed
        (:meth:`DriftTracker.measure_ahead`); :meth:`finish_ahead` completes
        it. Results are the same as without it.
        """
        step, reason, tracker = self._register(frame, seq, events)
        if next_frame is not None:
            self._register_ahead(next_frame, frame, events)
        t = frame.t_mid_s
        if self.t_ref_s is None and not reason:
            self.t_ref_s = t
        t_ref = self.t_ref_s if self.t_ref_s is not None else t
        offset = offset_change_nm(t, t_ref, events)[0]
        pos = FramePosition(offset=offset, reason=reason)
        if self._tracker is not None:
            # the frame the tracker measures against (for a refused frame too)
            pos.reference_key = self._keys.get(self._tracker.keyframe_index)
        if not reason and step is None and tracker is not None:
            self._place_reference(frame, seq, tracker, pos, prediction_nm, n_fed, held, events)
        elif step is not None and tracker is not None:
            self._place_measured(frame, seq, tracker, step, pos, events, held)
        pos.chain = self.chain
        pos.p = pos.m + offset
        if np.all(np.isfinite(pos.p)):
            self.last_p_nm = pos.p
        return pos

    def _register(
        self, frame: Frame, seq: int, events: Sequence[Event]
    ) -> tuple[TrackStep | None, str, DriftTracker | None]:
        """Registration against the tracker's reference: ``(step, reason, tracker)``.

        A new tracker (a new reference) is made for the first frame, after
        :meth:`request_reset`, and when the frame's shape or pixel size changed.
        """
        key = (frame.shape, frame.pixel_size_nm)
        if not self._reset_requested and key != self._tracker_key and key in self._parked:
            self._take_up(key, seq)
        new_reference = self._tracker is None or self._reset_requested or key != self._tracker_key
        tracker = self._tracker
        moved = (0.0, 0.0)
        if tracker is None or new_reference:
            tracker = self._tracker_factory(frame.pixel_size_nm)
            if self._tracker is None and self._first_prior_px is not None:
                tracker.expect(self._first_prior_px)
        elif self._last_t_s is not None:
            moved = _content_moved_px(frame, self._last_t_s, events)
        try:
            step = tracker.update(frame.heights_nm, moved_px=moved)
        except InputError as err:
            # The frame was refused before it touched anything: the current
            # reference (if any) stays, and a pending reset stays pending.
            reason = f"registration failed: {err}"
            log.warning("frame %d (instrument %d): %s", seq, frame.index, reason)
            return None, reason, None
        if new_reference:
            if not self._reset_requested:
                self._park()
                log.info(
                    "frame %d: scan geometry %s: a new reference for it, its position "
                    "carried across from the drift trajectory", seq, _geometry(key),
                )  # fmt: skip
            self._tracker, self._tracker_key, self._reset_requested = tracker, key, False
            self._keys = {}
        return step, "", tracker

    def _park(self) -> None:
        """Keep the current reference for its scan geometry's return."""
        if self._tracker is None or self._tracker_key is None:
            return
        self._parked[self._tracker_key] = _Parked(
            self._tracker,
            self._base_nm,
            self._keys,
            self._last_t_s,
            self.chain,
            self._chain_sigma_nm,
        )
        while len(self._parked) > _GEOMETRIES_KEPT:
            self._parked.pop(next(iter(self._parked)))

    def _take_up(self, key: GeometryKey, seq: int) -> None:
        """The frame's scan geometry was seen before: park the current reference
        and take up that geometry's, so its position chain goes on."""
        self._park()
        back = self._parked.pop(key)
        self._tracker, self._tracker_key = back.tracker, key
        self._base_nm, self._keys, self._last_t_s = back.base_nm, back.keys, back.last_t_s
        self.chain, self._chain_sigma_nm = back.chain, back.chain_sigma_nm
        log.info(
            "frame %d: scan geometry %s again: measured against its reference (frame %s)",
            seq, _geometry(key), self._keys.get(back.tracker.keyframe_index, "?"),
        )  # fmt: skip

    def _register_ahead(self, frame: Frame, last: Frame, events: Sequence[Event]) -> None:
        """Start registering ``frame`` against the current tracker, with the
        commanded motion :meth:`_register` will give it if ``last`` (the frame
        just registered) is remembered; if that turns out otherwise, or
        events arrive before it, the update differs and measures afresh."""
        tracker = self._tracker
        if (
            tracker is None
            or self._reset_requested
            or (frame.shape, frame.pixel_size_nm) != self._tracker_key
        ):
            return
        moved = _content_moved_px(frame, last.t_mid_s, events)
        tracker.measure_ahead(frame.heights_nm, moved_px=moved)

    def finish_ahead(self) -> None:
        """Complete the registration :meth:`locate` started for the next
        frame, so that no worker runs on (see :meth:`DriftTracker.finish_ahead`)."""
        if self._tracker is not None:
            self._tracker.finish_ahead()

    def _knot_times(self, tracker: DriftTracker, timing: _Timing, dy_px: float) -> FloatArray:
        """Scan times of the block rows of a frame whose content sits ``dy_px``
        below the reference grid."""
        return _sorted_unique(timing.times_at(tracker.block_rows_px + dy_px))

    def _remember(
        self, tracker_index: int, seq: int, frame: Frame, *, in_use: int | None = None
    ) -> None:
        """Map the tracker's frame ``tracker_index`` to ``seq`` and keep its
        timing; ``in_use``: a tracker index still needed by the caller (the
        reference of the frame being placed)."""
        self._keys[tracker_index] = seq
        self._timings[seq] = _Timing(
            frame.t_start_s, frame.t_end_s, frame.shape[0], frame.direction
        )
        if len(self._keys) > _TIMINGS_KEPT:
            # Later frames are measured against the keyframe or newer frames:
            # keep those, so a daemon's memory does not grow with its run.
            newest = sorted(self._keys)[-(_TIMINGS_KEPT // 2) :]
            kept = set(newest)
            if self._tracker is not None:
                kept.add(self._tracker.keyframe_index)
            if in_use is not None:
                kept.add(in_use)
            self._keys = {i: k for i, k in self._keys.items() if i in kept}
            values = set(self._keys.values())
            for parked in self._parked.values():
                values.update(parked.keys.values())
            self._timings = {k: v for k, v in self._timings.items() if k in values}
        self._last_t_s = frame.t_mid_s

    def _add_to_trajectory(
        self,
        seq: int,
        frame: Frame,
        knots: FloatArray,
        constraints: list[BandConstraint],
        events: Sequence[Event],
        *,
        reference: bool = False,
    ) -> FrameTrajectory | None:
        """Add the frame to the drift trajectory (``reference``: a new
        reference whose position is estimated, which starts a chain); None
        if it cannot be added."""
        for e in events:
            # A tip change shifts the image at once: the trajectory may jump there.
            if (
                e.kind is EventKind.TIP_CHANGE
                and e.t_s > self._breaks_to_s
                and (e.t_s <= frame.t_end_s)
            ):
                self.trajectory.add_break(e.t_s)
        self._breaks_to_s = max(self._breaks_to_s, frame.t_end_s)
        if not self._q_set and len(self.trajectory) == 0:
            self.trajectory.q = default_q(frame.t_end_s - frame.t_start_s)
            self._q_set = True
        try:
            if reference:
                return self.trajectory.add_reference(
                    seq, knots, sign=_sign(frame.direction), t_mid_s=frame.t_mid_s
                )
            return self.trajectory.add_frame(
                seq,
                knots,
                sign=_sign(frame.direction),
                t_mid_s=frame.t_mid_s,
                constraints=constraints,
            )
        except ValueError as err:
            log.warning("frame %d: not added to the drift trajectory (%s)", seq, err)
            return None

    def _place_reference(
        self,
        frame: Frame,
        seq: int,
        tracker: DriftTracker,
        pos: FramePosition,
        prediction_nm: FloatArray,
        n_fed: int,
        held: bool,
        events: Sequence[Event],
    ) -> None:
        """The frame is the new reference: p = 0 for the session reference;
        otherwise a new chain, its p estimated from the trajectory continued
        from the frames before it and held there (see the module docstring)."""
        self._remember(tracker.frames_seen - 1, seq, frame)
        knots = self._knot_times(tracker, self._timings[seq], 0.0)
        first = self.last_p_nm is None and n_fed == 0 and len(self.trajectory) == 0
        # A reference has no measurement of its own: its samples are not
        # known yet, so it reports none (the smoothed trajectory has them).
        if first:
            self._add_to_trajectory(seq, frame, knots, [], events)
            p_est = np.zeros(2)
            pos.reason = "reference"
            pos.fed = not held
            pos.sigma = 0.0
        else:
            traj = self._add_to_trajectory(seq, frame, knots, [], events, reference=True)
            if traj is not None:
                p_est, pos.sigma = traj.mid_nm, traj.mid_sigma_nm
            elif np.all(np.isfinite(prediction_nm)):
                p_est = prediction_nm
            elif self.last_p_nm is not None:
                p_est = self.last_p_nm
            else:
                p_est = np.zeros(2)
            pos.reason = "new reference (position estimated)"
            self._chains += 1
            self.chain = self._chains
            self._chain_sigma_nm = pos.sigma
        pos.m = p_est - pos.offset
        self._base_nm = pos.m.copy()
        pos.reference_image = np.asarray(frame.heights_nm, dtype=np.float32)

    def _moves_during(self, events: Sequence[Event], *timings: _Timing) -> bool:
        """Whether an offset move was logged while one of ``timings`` was scanned.

        The move times are kept sorted and extended with the entries appended
        since the last call (the model's history is append-only), so a long
        run does not rescan its whole event log every frame.
        """
        if events is not self._moves_of or len(events) < self._moves_seen:
            self._moves_of, self._moves_seen, self._move_times = events, 0, []
        for e in events[self._moves_seen :]:
            if e.kind is EventKind.OFFSET_MOVE:
                bisect.insort(self._move_times, e.t_s)
        self._moves_seen = len(events)
        for timing in timings:
            k = bisect.bisect_left(self._move_times, timing.t_start_s)
            if k < len(self._move_times) and self._move_times[k] <= timing.t_end_s:
                return True
        return False

    def _constraints(
        self,
        frame: Frame,
        tracker: DriftTracker,
        step: TrackStep,
        events: Sequence[Event],
    ) -> tuple[list[BandConstraint], float] | None:
        """Block-row constraints of an accepted measurement, and the mean row
        motion (px); None if its reference is not in the trajectory or no
        block row was scanned at one offset."""
        ref_key = self._keys.get(step.reference_index)
        timing_ref = None if ref_key is None else self._timings.get(ref_key)
        if ref_key is None or timing_ref is None or ref_key not in self.trajectory.frames:
            return None
        meas = step.measurement
        fld = meas.field
        # each block row's vector applies where its blocks' texture is, not
        # at the windows' centre row (BlockField.weight_centres_px)
        n_valid, levels, counts, means, at = fld.valid_row_means_px()
        if n_valid == 0:
            return None
        timing_cur = _Timing(frame.t_start_s, frame.t_end_s, frame.shape[0], frame.direction)
        t_cur = timing_cur.times_at(at + means[:, 1])
        t_ref = timing_ref.times_at(at)
        px, py = frame.pixel_size_nm
        sigma_frame = float(meas.sigma_nm) if math.isfinite(meas.sigma_nm) else 0.0
        sigmas = sigma_frame * np.sqrt(n_valid / counts)
        values = means * np.array([px, py]) + offset_change_nm(t_cur, t_ref, events)
        # A block row whose lines were scanned partly before and partly after
        # an offset move (in this frame or in its reference) holds content
        # from two offsets: its vector is neither, so it is left out.
        clean = np.ones(levels.size, dtype=bool)
        if self._moves_during(events, timing_ref, timing_cur):
            grid = tracker.block_rows_px
            half = 0.5 * float(np.min(np.diff(grid))) if grid.size > 1 else 0.5 * frame.shape[0]
            # the block rows' span, and the rows their vectors are timed at
            below = np.minimum(levels - half, at)
            above = np.maximum(levels + half, at)
            lo = np.concatenate([timing_cur.times_at(below + means[:, 1]),
                                 timing_ref.times_at(below)])  # fmt: skip
            hi = np.concatenate([timing_cur.times_at(above + means[:, 1]),
                                 timing_ref.times_at(above)])  # fmt: skip
            moved = np.any(offset_change_nm(hi, lo, events) != 0.0, axis=1)
            clean = ~(moved[: levels.size] | moved[levels.size :])
            if not clean.any():
                return None
        out = [
            BandConstraint(
                ref_key=ref_key,
                t_s=float(t_cur[k]),
                t_ref_s=float(t_ref[k]),
                value_nm=(float(values[k, 0]), float(values[k, 1])),
                sigma_nm=float(sigmas[k]),
            )
            for k in np.nonzero(clean)[0]
        ]
        valid = np.asarray(fld.valid, dtype=bool)
        return out, float(np.asarray(fld.vectors_px, dtype=np.float64)[valid, 1].mean())

    def _place_measured(
        self,
        frame: Frame,
        seq: int,
        tracker: DriftTracker,
        step: TrackStep,
        pos: FramePosition,
        events: Sequence[Event],
        held: bool,
    ) -> None:
        """A measured frame: increment since the previous accepted frame, the
        measurement against the reference (keyframe), and the trajectory."""
        inc, meas = step.increment, step.measurement
        accepted = bool(step.accepted)
        pos.increment = inc
        pos.reference_key = self._keys.get(step.reference_index)
        pos.dx, pos.dy = float(inc.dx_nm), float(inc.dy_nm)
        pos.measurement_sigma = float(meas.sigma_nm)
        # without the trajectory: the measurement's σ, and the chain reference's
        pos.sigma = math.hypot(self._chain_sigma_nm, pos.measurement_sigma)
        pos.valid_blocks, pos.total_blocks = int(meas.valid_blocks), int(meas.total_blocks)
        pos.keyframe_index = int(step.keyframe_index)
        pos.reanchored = bool(step.reanchored)
        pos.field = summarise_field(inc, frame.pixel_size_nm)
        min_blocks = self.config.service.min_valid_blocks
        low = (not accepted) or pos.valid_blocks < min_blocks
        if accepted:
            pos.m = self._base_nm + np.asarray(step.position_nm, dtype=np.float64).reshape(2)
            if pos.reanchored or self.config.registration.reference == "consecutive":
                pos.reference_image = np.asarray(frame.heights_nm, dtype=np.float32)
            # The tracker moved on to this frame (it may be the new keyframe).
            self._remember(step.frame_index, seq, frame, in_use=step.reference_index)
            made = None if low else self._constraints(frame, tracker, step, events)
            if made is not None:
                constraints, dy_px = made
                knots = self._knot_times(tracker, self._timings[seq], dy_px)
                traj = self._add_to_trajectory(seq, frame, knots, constraints, events)
                if traj is not None:
                    pos.trajectory = traj
                    # p from the trajectory at mid-scan time; m keeps its meaning.
                    pos.m = traj.mid_nm - pos.offset
                    pos.sigma = traj.mid_sigma_nm
        else:
            pos.dx = pos.dy = math.nan
            pos.reason = f"measurement rejected: {meas.reason or 'invalid'}"
        if low and not pos.reason:
            pos.reason = (
                f"low confidence: {pos.valid_blocks} valid blocks < "
                f"service.min_valid_blocks={min_blocks}"
            )
        pos.fed = not low and not held and bool(np.all(np.isfinite(pos.m)))


def _geometry(key: GeometryKey) -> str:
    (rows, cols), (px, py) = key
    return f"{cols}x{rows} px at {px:.4g} x {py:.4g} nm/px"


def _content_moved_px(frame: Frame, since_s: float, events: Sequence[Event]) -> tuple[float, float]:
    """How far the commanded offset moved the image content ``(x, y)`` from
    ``since_s`` to ``frame``'s mid-scan time, px: content moves by −ΔO for a
    commanded move of +ΔO (the tracker's ``moved_px``)."""
    d = offset_change_nm(frame.t_mid_s, since_s, events)[0]
    return (-float(d[0]) / frame.pixel_size_nm[0], -float(d[1]) / frame.pixel_size_nm[1])


def summarise_field(inc: Any, pixel_size_nm: tuple[float, float]) -> FieldSummary | None:
    """Mean, spread and confidence of a DriftResult's valid block vectors (nm)."""
    fld = getattr(inc, "field", None)
    if fld is None:
        return None
    # the mean and (population) spread of the blocks the drift was combined from
    n, stats = fld.valid_mean_std_px(ddof=0)
    valid = np.asarray(fld.valid, dtype=bool).reshape(-1)
    conf = np.sort(np.asarray(fld.confidence, dtype=np.float64).reshape(-1)[valid])
    median = 0.5 * (float(conf[(n - 1) // 2]) + float(conf[n // 2])) if n else math.nan
    px, py = pixel_size_nm

    def finite(v: float) -> float | None:
        return v if math.isfinite(v) else None

    # Numbers computed here (NaN where no block is valid, None on the wire):
    # the model needs no validation.
    return FieldSummary.model_construct(
        total_blocks=int(valid.size),
        valid_blocks=n,
        mean_dx_nm=finite(float(stats[0]) * px),
        mean_dy_nm=finite(float(stats[1]) * py),
        std_dx_nm=finite(float(stats[2]) * abs(px)),
        std_dy_nm=finite(float(stats[3]) * abs(py)),
        median_confidence=finite(median),
    )
