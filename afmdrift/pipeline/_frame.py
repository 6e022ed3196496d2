"""The per-frame pipeline shared by the daemon, replay and diagnose.

For each new frame, in named stages (:meth:`FramePipeline.process`): release
the channels and events logged up to the end of the frame into the model's
history (:class:`~afmdrift.model.HistoryFeed`), predict p for the frame before
it is seen, measure it against the tracker's reference (block phase
correlation), turn the measured image position into a drift position p by
adding back the commanded offset moves, update the predictor and rebuild the
continuous offset curve d(t), and make the frame's record. The daemon calls
:meth:`FramePipeline.process` in a worker thread for each new frame; a tool
that holds a whole recording (``afmdrift replay``, and so ``afmdrift
diagnose``, ``evaluate``, ``correct``, ``measure``) iterates
:meth:`FramePipeline.run`, which reads the recording one frame ahead itself.
All of them run the same code.

Positions (see ``afmdrift.model._positions`` for the sign convention)::

    m_k  measured image position of frame k relative to the session reference
    p_k = m_k + O(t_k) − O(t_ref)      drift position, p(t_ref) = 0

When the registration reference is replaced (``reset_reference``, a changed
frame shape or pixel size, an instrument restart or another instrument, a
resumed service without its reference image) the new reference's drift
position is not measured; it is estimated from the drift trajectory (the
model's prediction, or the last position, if the trajectory has none) so p
stays continuous, and the frame does not feed the model. It starts a new
chain of positions, held at that estimate (``DriftPositions``).
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel

from afmdrift.config import AfmdriftConfig
from afmdrift.errors import InputError
from afmdrift.model import (
    FeedBatch,
    FrameTrajectory,
    History,
    HistoryFeed,
    Observation,
    OffsetCurve,
    Predictor,
    make_predictor,
    reconstruct_offset,
)
from afmdrift.pipeline._dewarp import dewarp_frame, image_positions
from afmdrift.pipeline._positions import (
    DriftPositions,
    FramePosition,
    TrackerFactory,
    summarise_field,
)
from afmdrift.pipeline._records import FrameRecord, ResumeState, observation_from_record
from afmdrift.records import ChannelSample, Event, Frame, LoggedEvent, ScanDirection
from afmdrift.wire import FieldSummary

FloatArray = npt.NDArray[np.float64]

__all__ = ["FrameOutcome", "FramePipeline", "summarise_field", "with_next"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class FrameOutcome:
    """Result of :meth:`FramePipeline.process` for one frame."""

    record: FrameRecord
    curve: OffsetCurve | None
    curve_dict: dict[str, Any] | None
    predictor_name: str
    predictor_state: dict[str, Any] | None
    field: FieldSummary | None
    reference: npt.NDArray[np.float32] | None
    image: npt.NDArray[np.floating]
    low_confidence: bool
    #: Channels and events that reached the model's history with this frame.
    history: FeedBatch
    #: The frame's drift trajectory samples (causal), if it has any.
    trajectory: FrameTrajectory | None = None
    #: The frame de-warped by those samples (``service.archive_corrected``).
    corrected: npt.NDArray[np.float32] | None = None
    #: Where the frame sits: registration detail, trajectory, reference.
    position: FramePosition | None = None


@dataclass(frozen=True, slots=True)
class _Fed:
    fed: bool
    reason: str


class FramePipeline:
    """Registration → drift position → prediction score → model update → d(t).

    Parameters
    ----------
    config : AfmdriftConfig
        Uses ``registration``, ``model`` and ``service`` sections.
    tracker_factory : callable, optional
        ``pixel_size_nm -> tracker`` with ``update(image) -> TrackStep | None``;
        default :class:`afmdrift.registration.DriftTracker`.
    predictor : Predictor, optional
        Default ``afmdrift.model.make_predictor(config.model.predictor, config.model)``.
    keep_trajectory : bool
        Keep every frame of the drift trajectory for its smoothed estimate
        (replay, de-warping); the daemon forgets what it no longer needs.
    model : bool
        Feed the predictor and build d(t) (default). ``afmdrift measure`` on a
        stack reports drift positions only and skips this stage: the
        positions come from the same component either way.
    first_prior_px : (float, float), optional
        Expected drift of the first frame after the first, px (``--prior-px``):
        it centres the block search until a frame is accepted; later frames
        take the tracker's prediction.

    Notes
    -----
    Not thread-safe: one thread at a time (the daemon's single worker thread).
    """

    def __init__(
        self,
        *,
        config: AfmdriftConfig,
        tracker_factory: TrackerFactory | None = None,
        predictor: Predictor | None = None,
        keep_trajectory: bool = False,
        model: bool = True,
        first_prior_px: tuple[float, float] | None = None,
    ) -> None:
        self.config = config
        self.model = model
        self.positions = DriftPositions(
            config=config,
            tracker_factory=tracker_factory,
            keep_trajectory=keep_trajectory,
            first_prior_px=first_prior_px,
        )
        self.predictor = predictor if predictor is not None else self._make_predictor(config)
        self.feed = HistoryFeed()
        self.observations: deque[Observation] = deque(maxlen=config.service.training_window)
        self.n_fed = 0
        self.curve: OffsetCurve | None = None
        #: The last frame processed (-1: none yet).
        self.last_seq = -1
        # After a model change, d(t) hands over to the new model until this time.
        self._handover_until_s = -math.inf
        self._sample_interval_s = 1.0 / config.service.offset_rate_hz

    @property
    def history(self) -> History:
        """Channels and events the model has seen (up to the last frame's end)."""
        return self.feed.history

    @property
    def t_ref_s(self) -> float | None:
        """Mid-scan time of the session reference frame (p = 0), once known."""
        return self.positions.t_ref_s

    # ------------------------------------------------------------------ factories

    @staticmethod
    def _make_predictor(config: AfmdriftConfig) -> Predictor:
        return make_predictor(config.model.predictor, config.model)

    # ------------------------------------------------------------------ inputs

    def push(
        self, channels: Iterable[ChannelSample] = (), events: Iterable[Event | LoggedEvent] = ()
    ) -> None:
        """Make channel samples and event-log entries known (as they arrive, or a
        whole session at once); each reaches the model with the first frame that
        ends after it was logged."""
        self.feed.push(channels, events)

    def request_reset(self) -> None:
        """Make the next frame the registration reference (p stays continuous)."""
        self.positions.request_reset()

    def reload_model(self, predictor: Predictor) -> int:
        """Replace the predictor and refit it on the kept observations; return
        their count (:meth:`refit`, then :meth:`use_model`)."""
        n = self.refit(predictor)
        self.use_model(predictor)
        return n

    def refit(self, predictor: Predictor) -> int:
        """Fit a fresh ``predictor`` on the kept observations and the history;
        return their count. The pipeline itself is not changed."""
        for obs in self.observations:
            predictor.update(obs, self.history)
        return len(self.observations)

    def use_model(self, predictor: Predictor, handover: Handover | None = None) -> None:
        """Predict with ``predictor`` (fitted by :meth:`refit`) from now on.

        With ``handover`` (:meth:`plan_handover` for this predictor; the
        daemon's model changes) d(t) is its curve, and frames measured before
        the hand-over ends keep handing over to its end. Without it, the curve
        is rebuilt at the last observation's time.
        """
        self.predictor = predictor
        self.n_fed = len(self.observations)
        if not self.observations:
            self.curve = None
        elif handover is None or handover.curve is None:
            self.curve = self._build_curve(self.observations[-1].t_s)
        else:
            self.curve = handover.curve
            self._handover_until_s = handover.until_s
            self._sample_interval_s = handover.sample_interval_s

    def resume(
        self,
        state: ResumeState,
        *,
        records: Sequence[FrameRecord],
        channels: Sequence[ChannelSample],
        events: Sequence[LoggedEvent],
    ) -> None:
        """Continue after a restart from what the store committed.

        ``records`` are recent frame records (oldest first; those that fed the
        model rebuild the refit window). The tracker is re-primed with the
        stored reference image when there is one; otherwise the next frame
        becomes a new reference.
        """
        self.feed.push(channels, events)
        self.feed.advance(state.last.t_end_s)
        fed = [r for r in records if r.fed_model]
        ref = state.reference_record
        ref_direction = ScanDirection(ref.direction) if ref is not None else None
        for r in fed[-self.config.service.training_window :]:
            self.observations.append(observation_from_record(r, ref_direction))
        if self._load_predictor_state(state):
            self.n_fed = len(fed)
        elif state.predictor_state is not None and self.observations:
            # The stored state is for another predictor, or damaged: this one
            # starts fresh, refitted on the kept observations (as reload_model).
            self.n_fed = self.reload_model(self.predictor)
            log.warning(
                "predictor %r started fresh, refitted on the %d observations kept in the store",
                self.predictor.name,
                self.n_fed,
            )
        last = state.last
        self.positions.resume(
            t_ref_s=state.t_ref_s,
            last_p_nm=np.array([last.x_nm, last.y_nm])
            if math.isfinite(last.x_nm) and math.isfinite(last.y_nm)
            else None,
            reference=state.reference,
            reference_record=state.reference_record,
            reference_m_nm=(state.reference_x_nm, state.reference_y_nm),
        )
        if self.n_fed:
            curve = self._stored_curve(state)
            self.curve = curve if curve is not None else self._build_curve(last.t_end_s)

    def _load_predictor_state(self, state: ResumeState) -> bool:
        """Load the stored predictor state if it is this predictor's and readable."""
        if state.predictor_state is None:
            return False
        if state.predictor and state.predictor != self.predictor.name:
            log.warning(
                "the run store's model state is for predictor %r; [model] predictor is now %r",
                state.predictor,
                self.predictor.name,
            )
            return False
        try:
            if not self._same_config(state.predictor_state):
                log.warning(
                    "the run store's model state is for another configuration of %r "
                    "(its terms or settings differ)",
                    self.predictor.name,
                )
                return False
            self.predictor.load_state_dict(state.predictor_state)
        except (KeyError, ValueError, TypeError, IndexError) as err:
            log.warning(
                "the run store's model state cannot be loaded (%s: %s)", type(err).__name__, err
            )
            self.predictor = self._make_predictor(self.config)  # not half-loaded
            return False
        return True

    def _same_config(self, stored: dict[str, Any]) -> bool:
        """The stored state's configuration is this predictor's (one without a
        configuration of its own in its state matches any)."""
        own = getattr(self.predictor, "config", None)
        if not isinstance(own, BaseModel) or "config" not in stored:
            return True
        return bool(type(own).model_validate(stored["config"]) == own)

    @staticmethod
    def _stored_curve(state: ResumeState) -> OffsetCurve | None:
        if state.curve is None:
            return None
        try:
            return OffsetCurve.from_dict(state.curve)
        except InputError as err:
            log.warning("stored offset curve unusable (%s); rebuilding it", err)
            return None

    # ------------------------------------------------------------------ the frame

    def run(self, frames: Iterable[Frame]) -> Iterator[FrameOutcome]:
        """Run the pipeline over a recording: one outcome per frame, in order.

        Frame ``k`` gets ``seq=k`` and its curve is used from the end of its
        scan, as :meth:`process` does for a frame without ``t_now_s``. The
        recording is read one frame ahead: the next frame's block pass runs
        on the registration engine's workers while this frame's position and
        record are made (see :meth:`DriftPositions.locate`), and is complete
        before the outcome is yielded. Results are those of one
        :meth:`process` call per frame.
        """
        for k, frame, upcoming in with_next(frames):
            yield self._process(frame, seq=k, t_now_s=frame.t_end_s, ahead=upcoming)

    def process(
        self,
        frame: Frame,
        *,
        seq: int,
        epoch: int = 0,
        detected_wall_s: float | None = None,
        t_now_s: float | None = None,
        hold: str | None = None,
    ) -> FrameOutcome:
        """Run the whole pipeline on one frame. Bad input never raises; it is recorded.

        The stages, in the order every tool runs them: the history up to the
        end of the frame, the prediction made before the frame, registration,
        the drift position, the model update and d(t), the record.
        ``t_now_s`` is the instrument time from which the new curve is used
        (default: the end of the frame). ``hold`` is a reason why the frame is
        measured and recorded but must not feed the model (for example: the
        event log could not be read up to it, so commanded moves may be
        missing from its drift position; or ``"paused"`` by the operator).
        A recording that is already whole goes through :meth:`run` instead.
        """
        return self._process(
            frame, seq=seq, epoch=epoch, detected_wall_s=detected_wall_s, t_now_s=t_now_s,
            hold=hold, ahead=None,
        )  # fmt: skip

    def _process(
        self,
        frame: Frame,
        *,
        seq: int,
        epoch: int = 0,
        detected_wall_s: float | None = None,
        t_now_s: float | None,
        hold: str | None = None,
        ahead: Frame | None,
    ) -> FrameOutcome:
        """:meth:`process`, with the block pass of ``ahead`` (the frame the
        next call will be given) started once this frame is registered."""
        started = time.time() if detected_wall_s is None else detected_wall_s
        batch = self.feed.advance(frame.t_end_s)
        pred = self._predict(frame)
        held = hold is not None
        try:
            pos = self.positions.locate(
                frame, seq=seq, events=self.history.events, prediction_nm=pred[0],
                n_fed=self.n_fed, held=held, next_frame=ahead,
            )  # fmt: skip
            observed = _observed(frame, pos)
            fed = self._feed_model(frame, pos, observed, seq=seq, held=hold, t_now_s=t_now_s)
            record = _frame_record(
                frame, pos, pred, observed, seq=seq, epoch=epoch, fed=fed.fed,
                reason=fed.reason, started=started,
            )  # fmt: skip
        finally:
            if ahead is not None:
                self.positions.finish_ahead()
        self.last_seq = seq
        return FrameOutcome(
            record=record,
            curve=self.curve,
            curve_dict=None if self.curve is None else self.curve.to_dict(),
            predictor_name=self.predictor.name,
            predictor_state=self.predictor.state_dict() if fed.fed else None,
            field=pos.field,
            reference=pos.reference_image,
            image=frame.heights_nm,
            low_confidence=not fed.fed and not held and fed.reason not in ("reference",),
            history=batch,
            trajectory=pos.trajectory,
            corrected=self._corrected(frame, pos),
            position=pos,
        )

    def _corrected(self, frame: Frame, pos: FramePosition) -> npt.NDArray[np.float32] | None:
        """The frame de-warped by its causal trajectory, when the service keeps them."""
        traj = pos.trajectory
        if not self.config.service.archive_corrected or traj is None:
            return None
        t_ref = self.t_ref_s if self.t_ref_s is not None else frame.t_mid_s
        m = image_positions(traj, self.history.events, t_ref)
        return dewarp_frame(frame, traj.t_s, m, fill="nan")

    def _feed_model(
        self,
        frame: Frame,
        pos: FramePosition,
        observed: tuple[float, FloatArray, float],
        *,
        seq: int,
        held: str | None,
        t_now_s: float | None,
    ) -> _Fed:
        """Feed the drift position to the predictor and rebuild d(t) (unless ``held``:
        the reason it may not)."""
        reason = pos.reason
        if held is not None and not reason:
            reason = held
        fed = pos.fed
        if fed:
            t, xy, sigma = observed
            obs = Observation(
                t_s=t,
                x_nm=float(xy[0]),
                y_nm=float(xy[1]),
                sigma_nm=sigma,
                direction=frame.direction,
                frame=seq,
                reference_direction=self.positions.reference_direction,
            )
            if self.observations and obs.t_s <= self.observations[-1].t_s:
                reason = f"frame time {t:.3f} s is not after the last fed frame"
                log.warning("frame %d: %s; not fed to the model", seq, reason)
                fed = False
            elif not self.model:
                self.observations.append(obs)
            else:
                self.predictor.update(obs, self.history)
                self.observations.append(obs)
                self.n_fed += 1
                t_pub = frame.t_end_s if t_now_s is None else max(t_now_s, frame.t_end_s)
                self.curve = self._build_curve(t_pub)
        return _Fed(fed=fed, reason=reason)

    # ------------------------------------------------------------------ model

    def _predict(self, frame: Frame) -> tuple[npt.NDArray[np.float64], float]:
        """Prediction of the frame's mid-scan p, in its own scan direction, from
        the current model (NaN before any data)."""
        if self.n_fed == 0:
            return np.full(2, np.nan), math.nan
        at = Observation(frame.t_mid_s, 0.0, 0.0, 0.0, direction=frame.direction)
        try:
            mean, sig = self.predictor.predict_observation(at, self.history)
        except (ValueError, ArithmeticError) as err:
            log.warning("prediction at t=%.3f s failed: %s", frame.t_mid_s, err)
            return np.full(2, np.nan), math.nan
        return mean, float(np.hypot(sig[0], sig[1]) / math.sqrt(2.0))

    def _build_curve(self, t_now_s: float) -> OffsetCurve | None:
        """d(t) from now on, continuous in value and slope with the previous curve
        (still handing over after a model change while that lasts)."""
        if self.curve is not None and t_now_s < self._handover_until_s:
            plan = self.plan_handover(
                self.predictor, t_now_s=t_now_s, sample_interval_s=self._sample_interval_s,
                min_blend_s=self._handover_until_s - t_now_s,
            )  # fmt: skip
            if plan.curve is not None:
                self._handover_until_s = plan.until_s
                return plan.curve
        try:
            return reconstruct_offset(
                self.predictor,
                self.history,
                config=self.config.model,
                t_now_s=t_now_s,
                previous=self.curve,
            )
        except (ValueError, ArithmeticError) as err:
            log.warning(
                "offset curve at t=%.3f s failed: %s; keeping the previous one", t_now_s, err
            )
            return self.curve

    def plan_handover(
        self,
        predictor: Predictor,
        *,
        t_now_s: float,
        sample_interval_s: float,
        min_blend_s: float = 0.0,
        lead_s: float = 0.0,
    ) -> Handover:
        """d(t) from ``t_now_s`` on, handing over from the published curve to
        ``predictor``'s prediction with no step between two offset samples
        ``sample_interval_s`` apart (instrument time) larger than the bound
        (``docs/service.md``, *Changing the model*). Nothing is changed.

        The bound is max(the prediction's 1σ at ``t_now_s``,
        :data:`MIN_HANDOVER_STEP_NM`), or the step the published curve itself
        makes over one interval at ``t_now_s`` if that is larger (its slope
        goes on at first: the hand-over adds no step of its own beyond the
        bound). The hand-over time starts at
        1.5·|Δ|/(0.8·bound) sample intervals (Δ the new prediction minus the
        published value now; 1.5 the steepest slope of a cubic Hermite blend
        over its mean), at least one interval and ``min_blend_s``, and is
        doubled until the
        curve keeps the bound on a grid of a quarter interval.

        With ``lead_s`` the curve *is* the published one (its knots) up to
        ``t_now_s + lead_s`` and hands over from there, from its value and
        slope then: the offset stream takes the new curve up some time after
        it is planned (the store's commit, the event loop; at a simulator's
        speed-up that wall time is minutes of instrument time), and wherever
        before the lead it does, it sees no step. Without
        a published curve, with the sinc reconstruction (which does not start
        from the previous curve), or when the prediction fails, ``curve`` is
        ``None``: the pipeline builds its own.
        """
        previous = self.curve
        bound = MIN_HANDOVER_STEP_NM
        none = Handover(None, t_now_s, sample_interval_s, bound, math.nan)
        if previous is None or self.config.model.reconstruction != "hermite":
            return none
        try:
            now = predictor.predict_drift([t_now_s], self.history)
        except (ValueError, ArithmeticError) as err:
            log.warning("prediction at t=%.3f s failed: %s", t_now_s, err)
            return none
        t_start = t_now_s + max(lead_s, 0.0)
        sigma = float(np.hypot(*now.sigma_nm[0]) / math.sqrt(2.0))
        gap = float(np.hypot(*(now.mean_nm[0] - previous.at([t_start])[0])))
        bound = max(sigma if math.isfinite(sigma) else 0.0, MIN_HANDOVER_STEP_NM)
        tick_s = sample_interval_s
        own_step = largest_step_nm(previous, t_now_s, t_now_s, tick_s)
        allowed = max(bound, 1.05 * own_step)
        needed_s = 1.5 * gap * tick_s / (0.8 * bound) if math.isfinite(gap) else 0.0
        blend_s = max(min_blend_s, tick_s, needed_s)
        step, reached_s = math.inf, t_start
        for _ in range(_HANDOVER_TRIES):
            try:
                curve = reconstruct_offset(
                    predictor,
                    self.history,
                    config=self.config.model,
                    t_now_s=t_start,
                    previous=previous,
                    blend_s=blend_s,
                )
            except (ValueError, ArithmeticError) as err:
                log.warning("offset curve at t=%.3f s failed: %s", t_start, err)
                return none
            # the first knot after the start is on the new prediction (a
            # hand-over shorter than the curve's smallest knot spacing ends there)
            reached_s = float(curve.knot_t_s[1]) if curve.knot_t_s.size > 1 else t_start
            if t_start > t_now_s:
                curve = _published_until(previous, curve, t_now_s, t_start)
            step = largest_step_nm(curve, t_now_s, reached_s + 2 * tick_s, tick_s)
            if step <= allowed:
                break
            blend_s = 2.0 * max(blend_s, tick_s)
        else:
            log.warning(
                "d(t) hands over to the changed model with steps of %.3g nm (bound %.3g nm)",
                step,
                allowed,
            )
        return Handover(curve, max(reached_s, t_start + blend_s), sample_interval_s, allowed, step)


@dataclass(frozen=True, slots=True)
class Handover:
    """How d(t) goes over to a changed model (:meth:`FramePipeline.plan_handover`).

    ``curve`` is d(t) from the change on (``None``: no curve was published
    yet, or the prediction failed: the pipeline builds its own); it reaches
    the new model's prediction at ``until_s``. ``bound_nm`` is the largest
    step allowed between offset samples ``sample_interval_s`` apart
    (max(σ, :data:`MIN_HANDOVER_STEP_NM`), or the published curve's own step
    if larger) and ``step_nm`` the largest the curve makes (NaN without a
    curve).
    """

    curve: OffsetCurve | None
    until_s: float
    sample_interval_s: float
    bound_nm: float
    step_nm: float


#: The smallest bound of a step of d(t) between two offset samples while d(t)
#: hands over to a changed model, nm (the prediction's 1σ when larger).
MIN_HANDOVER_STEP_NM = 0.5
#: Hand-over times tried (each twice the last) before the bound is given up.
_HANDOVER_TRIES = 12
#: Most times :func:`largest_step_nm` evaluates (a longer span gets a coarser grid).
_STEP_GRID_MAX = 200_000


def _published_until(
    previous: OffsetCurve, curve: OffsetCurve, t_from_s: float, t_start_s: float
) -> OffsetCurve:
    """``curve`` (a Hermite curve starting at ``t_start_s`` from ``previous``'s
    value and slope there) preceded by ``previous``'s own knots from
    ``t_from_s``: on [t_from_s, t_start_s] it is ``previous`` exactly (a cubic
    segment is fixed by the values and slopes at its ends)."""
    k = previous.knot_t_s
    first = max(int(np.searchsorted(k, t_from_s, side="right")) - 1, 0)
    keep = np.arange(k.size)
    keep = keep[(keep >= first) & (k < t_start_s)]
    return OffsetCurve(
        "hermite",
        (t_from_s, curve.t_valid_s[1]),
        np.concatenate([k[keep], curve.knot_t_s]),
        np.concatenate([previous.knot_nm[keep], curve.knot_nm]),
        np.concatenate([previous.slope_nm_per_s[keep], curve.slope_nm_per_s]),
    )


def largest_step_nm(curve: OffsetCurve, t0_s: float, t1_s: float, tick_s: float) -> float:
    """The largest |d(t + tick_s) − d(t)| (Euclidean, nm) for t in [t0_s, t1_s],
    on a grid of a quarter of ``tick_s``: the largest step a stream of
    samples ``tick_s`` apart can see there."""
    n = max(math.ceil((t1_s - t0_s) / (0.25 * tick_s)), 1) + 1
    t = np.linspace(t0_s, t1_s, min(n, _STEP_GRID_MAX))
    steps = curve.at(t + tick_s) - curve.at(t)
    return float(np.max(np.hypot(steps[:, 0], steps[:, 1])))


def _observed(frame: Frame, pos: FramePosition) -> tuple[float, FloatArray, float]:
    """What the frame tells the model: the latest sample of its drift
    trajectory (the end of the scan, so the horizon to the next frame is
    shortest), or its mid-scan position where it has no trajectory.

    The uncertainty is that of the frame's own measurement (the registration's
    σ of its block mean against its reference), as before the trajectory. The
    trajectory's σ is that of p relative to the session reference: it grows
    along the keyframe chain and is shared by the frames measured against one
    keyframe, so as a weight it favoured the frames early in the chain (and a
    sample's own σ depends on which edge of the frame was scanned last);
    one-step prediction was worse with it on replayed graphite-paper and
    hidden-effect sessions.
    """
    sigma = pos.measurement_sigma if math.isfinite(pos.measurement_sigma) else pos.sigma
    sigma = sigma if math.isfinite(sigma) else 0.0
    traj = pos.trajectory
    if traj is not None and traj.t_s.size:
        k = int(np.argmax(traj.t_s))
        if np.all(np.isfinite(traj.xy_nm[k])):
            return float(traj.t_s[k]), np.asarray(traj.xy_nm[k], dtype=np.float64), sigma
    return frame.t_mid_s, pos.p, sigma


def _frame_record(
    frame: Frame,
    pos: FramePosition,
    pred: tuple[npt.NDArray[np.float64], float],
    observed: tuple[float, FloatArray, float],
    *,
    seq: int,
    epoch: int,
    fed: bool,
    reason: str,
    started: float,
) -> FrameRecord:
    """The store row of a processed frame (``observed``: what it tells the
    model, :func:`_observed`)."""
    finished = time.time()
    m, p, offset = pos.m, pos.p, pos.offset
    obs_t, obs_xy, obs_sigma = observed
    return FrameRecord(
        seq=seq,
        instrument_frame=frame.index,
        epoch=epoch,
        t_start_s=frame.t_start_s,
        t_end_s=frame.t_end_s,
        t_mid_s=frame.t_mid_s,
        direction=frame.direction.value,
        rows=frame.shape[0],
        cols=frame.shape[1],
        pixel_x_nm=frame.pixel_size_nm[0],
        pixel_y_nm=frame.pixel_size_nm[1],
        dx_nm=pos.dx,
        dy_nm=pos.dy,
        image_x_nm=float(m[0]),
        image_y_nm=float(m[1]),
        x_nm=float(p[0]),
        y_nm=float(p[1]),
        sigma_nm=pos.sigma,
        valid=math.isfinite(float(p[0])),
        fed_model=fed,
        reason=reason,
        valid_blocks=pos.valid_blocks,
        total_blocks=pos.total_blocks,
        keyframe_index=pos.keyframe_index,
        reanchored=pos.reanchored,
        pred_x_nm=float(pred[0][0]),
        pred_y_nm=float(pred[0][1]),
        pred_sigma_nm=float(pred[1]),
        offset_x_nm=float(offset[0]),
        offset_y_nm=float(offset[1]),
        wall_s=finished,
        latency_s=finished - started,
        field_json="null" if pos.field is None else pos.field.model_dump_json(),
        obs_t_s=obs_t if fed else math.nan,
        obs_x_nm=float(obs_xy[0]) if fed else math.nan,
        obs_y_nm=float(obs_xy[1]) if fed else math.nan,
        obs_sigma_nm=obs_sigma if fed else math.nan,
    )


def with_next(frames: Iterable[Frame]) -> Iterator[tuple[int, Frame, Frame | None]]:
    """``(k, frame, the next frame or None)`` over ``frames``, reading one
    frame ahead: how :meth:`FramePipeline.run` goes through a recording."""
    it = iter(frames)
    current = next(it, None)
    k = 0
    while current is not None:
        upcoming = next(it, None)
        yield k, current, upcoming
        current, k = upcoming, k + 1
