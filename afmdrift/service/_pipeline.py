"""The per-frame pipeline shared by the daemon and by replay.

For each new frame: measure it against the tracker's reference (block phase
correlation), turn the measured image position into a drift position p by
adding back the commanded offset moves, score the prediction made for this
frame before it arrived, update the predictor, and rebuild the continuous
offset curve d(t). :class:`FramePipeline` does exactly this, synchronously; the
daemon calls it in a worker thread, ``afmdrift replay`` calls it in a loop, so
both run the same code.

Positions (see ``afmdrift.model._positions`` for the sign convention)::

    m_k  measured image position of frame k relative to the session reference
    p_k = m_k + O(t_k) − O(t_ref)      drift position, p(t_ref) = 0

When the registration reference is replaced (``reset_reference``, a changed
frame shape or pixel size, an instrument restart, a resumed service without
its reference image) the new reference's drift position is not measured; it
is taken from the model's prediction (or the last position) so p stays
continuous, and the frame does not feed the model.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.config import AfmdriftConfig
from afmdrift.drivers._base import ChannelSample, Event, Frame
from afmdrift.errors import InputError
from afmdrift.model import History, Observation, OffsetCurve, Predictor
from afmdrift.model._positions import commanded_offset_nm
from afmdrift.registration import DriftTracker, TrackStep
from afmdrift.service._store import FrameRecord, ResumeState, RunStore
from afmdrift.service._wire import FieldSummary

__all__ = ["FrameOutcome", "FramePipeline", "process_and_record"]

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


TrackerFactory = Callable[[tuple[float, float]], DriftTracker]


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
    ) -> None:
        self.config = config
        self._tracker_factory = tracker_factory or self._default_tracker_factory
        self.predictor = predictor if predictor is not None else self._make_predictor(config)
        self.history = History()
        self.observations: deque[Observation] = deque(maxlen=config.service.training_window)
        self.n_fed = 0
        self._tracker: DriftTracker | None = None
        self._tracker_key: tuple[tuple[int, int], tuple[float, float]] | None = None
        self._base_nm = np.zeros(2)  # image position m of the tracker's reference
        self._t_ref_s: float | None = None  # session reference time (p = 0)
        self._last_p_nm: npt.NDArray[np.float64] | None = None
        self._reset_requested = False
        self.curve: OffsetCurve | None = None

    @property
    def t_ref_s(self) -> float | None:
        """Mid-scan time of the session reference frame (p = 0), once known."""
        return self._t_ref_s

    # ------------------------------------------------------------------ factories

    def _default_tracker_factory(self, pixel_size_nm: tuple[float, float]) -> DriftTracker:
        return DriftTracker(pixel_size_nm=pixel_size_nm, config=self.config.registration)

    @staticmethod
    def _make_predictor(config: AfmdriftConfig) -> Predictor:
        from afmdrift.model import make_predictor

        return make_predictor(config.model.predictor, config.model)

    # ------------------------------------------------------------------ inputs

    def ingest(self, channels: Sequence[ChannelSample], events: Sequence[Event]) -> None:
        """Add channel samples and event-log entries that arrived since the last call."""
        for sample in channels:
            if self.history.channel_t_s and sample.t_s < self.history.channel_t_s[-1]:
                log.warning("channel sample at t=%.3f s is out of order; dropped", sample.t_s)
                continue
            self.history.add_channels(sample)
        if events:
            self.history.add_events(events)

    def request_reset(self) -> None:
        """Make the next frame the registration reference (p stays continuous)."""
        self._reset_requested = True

    def reload_model(self, predictor: Predictor) -> int:
        """Replace the predictor and refit it on the kept observations; return their count."""
        for obs in self.observations:
            predictor.update(obs, self.history)
        self.predictor = predictor
        self.n_fed = len(self.observations)
        self.curve = self._build_curve(self.observations[-1].t_s) if self.observations else None
        return self.n_fed

    def resume(
        self,
        state: ResumeState,
        *,
        records: Sequence[FrameRecord],
        channels: Sequence[ChannelSample],
        events: Sequence[Event],
    ) -> None:
        """Continue after a restart from what the store committed.

        ``records`` are recent frame records (oldest first; those that fed the
        model rebuild the refit window). The tracker is re-primed with the
        stored reference image when there is one; otherwise the next frame
        becomes a new reference.
        """
        self.ingest(channels, events)
        if state.predictor_state is not None:
            self.predictor.load_state_dict(state.predictor_state)
        fed = [r for r in records if r.fed_model]
        for r in fed[-self.config.service.training_window :]:
            self.observations.append(_observation(r))
        self.n_fed = len(fed) if state.predictor_state is not None else 0
        self._t_ref_s = state.t_ref_s
        last = state.last
        if math.isfinite(last.x_nm) and math.isfinite(last.y_nm):
            self._last_p_nm = np.array([last.x_nm, last.y_nm])
        if state.reference is not None:
            ref = state.reference
            key = (ref.shape[0], ref.shape[1]), (last.pixel_x_nm, last.pixel_y_nm)
            self._tracker = self._tracker_factory(key[1])
            self._tracker.update(ref)
            self._tracker_key = (key[0], key[1])
            self._base_nm = np.array([state.reference_x_nm, state.reference_y_nm])
        if self.n_fed:
            curve = self._stored_curve(state)
            self.curve = curve if curve is not None else self._build_curve(last.t_end_s)

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

    def process(
        self,
        frame: Frame,
        *,
        seq: int,
        epoch: int = 0,
        detected_wall_s: float | None = None,
        paused: bool = False,
        t_now_s: float | None = None,
    ) -> FrameOutcome:
        """Run the whole pipeline on one frame. Bad input never raises; it is recorded.

        ``t_now_s`` is the instrument time from which the new curve is used
        (default: the end of the frame).
        """
        started = time.time() if detected_wall_s is None else detected_wall_s
        t = frame.t_mid_s
        pred = self._predict(t)
        image = frame.heights_nm
        key = (frame.shape, frame.pixel_size_nm)
        new_reference = self._tracker is None or self._reset_requested or key != self._tracker_key
        reason = ""
        step: TrackStep | None = None
        reference_image: npt.NDArray[np.float32] | None = None
        tracker = self._tracker
        if tracker is None or new_reference:
            tracker = self._tracker = self._tracker_factory(frame.pixel_size_nm)
            self._tracker_key = key
            self._reset_requested = False
        try:
            step = tracker.update(image)
        except InputError as err:
            reason = f"registration failed: {err}"
            log.warning("frame %d (instrument %d): %s", seq, frame.index, reason)
            if new_reference:
                self._tracker = None  # the next frame tries again to become the reference
        if self._t_ref_s is None and not reason:
            self._t_ref_s = t
        t_ref = self._t_ref_s if self._t_ref_s is not None else t
        offset = (
            commanded_offset_nm([t], self.history.events)[0]
            - (commanded_offset_nm([t_ref], self.history.events)[0])
        )
        dx = dy = sigma = math.nan
        valid_blocks = total_blocks = 0
        keyframe_index = 0
        reanchored = False
        field: FieldSummary | None = None
        m = np.full(2, np.nan)
        fed = False
        if not reason and step is None:
            # This frame is the new reference: its position is known (p = 0 for
            # the session reference) or estimated (prediction or last position).
            if self._last_p_nm is None and self.n_fed == 0:
                p_est = np.zeros(2)
                reason = "reference"
                fed = not paused
                sigma = 0.0
            else:
                if np.all(np.isfinite(pred[0])):
                    p_est = pred[0]
                elif self._last_p_nm is not None:
                    p_est = self._last_p_nm
                else:
                    p_est = np.zeros(2)
                reason = "new reference (position estimated)"
            m = p_est - offset
            self._base_nm = m.copy()
            reference_image = np.asarray(image, dtype=np.float32)
        elif step is not None:
            # increment: since the previous accepted frame; measurement: against
            # the reference (keyframe), which is what the position rests on.
            inc, meas = step.increment, step.measurement
            accepted = bool(step.accepted)
            dx, dy = float(inc.dx_nm), float(inc.dy_nm)
            sigma = float(meas.sigma_nm)
            valid_blocks, total_blocks = int(meas.valid_blocks), int(meas.total_blocks)
            keyframe_index = int(step.keyframe_index)
            reanchored = bool(step.reanchored)
            field = _summarise_field(inc, frame.pixel_size_nm)
            if accepted:
                m = self._base_nm + np.asarray(step.position_nm, dtype=np.float64).reshape(2)
                if reanchored or self.config.registration.reference == "consecutive":
                    reference_image = np.asarray(image, dtype=np.float32)
            else:
                dx = dy = math.nan
                reason = f"measurement rejected: {meas.reason or 'invalid'}"
            low = (not accepted) or valid_blocks < self.config.service.min_valid_blocks
            if low and not reason:
                reason = (
                    f"low confidence: {valid_blocks} valid blocks < "
                    f"service.min_valid_blocks={self.config.service.min_valid_blocks}"
                )
            fed = not low and not paused and bool(np.all(np.isfinite(m)))
        p = m + offset
        if paused and not reason:
            reason = "paused"
        obs: Observation | None = None
        if fed:
            obs = Observation(
                t_s=t,
                x_nm=float(p[0]),
                y_nm=float(p[1]),
                sigma_nm=sigma if math.isfinite(sigma) else 0.0,
                direction=frame.direction,
                frame=seq,
            )
            if self.observations and obs.t_s <= self.observations[-1].t_s:
                reason = f"frame time {t:.3f} s is not after the last fed frame"
                log.warning("frame %d: %s; not fed to the model", seq, reason)
                fed = False
        if fed and obs is not None:
            self.predictor.update(obs, self.history)
            self.observations.append(obs)
            self.n_fed += 1
            t_pub = frame.t_end_s if t_now_s is None else max(t_now_s, frame.t_end_s)
            self.curve = self._build_curve(t_pub)
        if np.all(np.isfinite(p)):
            self._last_p_nm = p
        finished = time.time()
        record = FrameRecord(
            seq=seq,
            instrument_frame=frame.index,
            epoch=epoch,
            t_start_s=frame.t_start_s,
            t_end_s=frame.t_end_s,
            t_mid_s=t,
            direction=frame.direction.value,
            rows=frame.shape[0],
            cols=frame.shape[1],
            pixel_x_nm=frame.pixel_size_nm[0],
            pixel_y_nm=frame.pixel_size_nm[1],
            dx_nm=dx,
            dy_nm=dy,
            image_x_nm=float(m[0]),
            image_y_nm=float(m[1]),
            x_nm=float(p[0]),
            y_nm=float(p[1]),
            sigma_nm=sigma,
            valid=math.isfinite(float(p[0])),
            fed_model=fed,
            reason=reason,
            valid_blocks=valid_blocks,
            total_blocks=total_blocks,
            keyframe_index=keyframe_index,
            reanchored=reanchored,
            pred_x_nm=float(pred[0][0]),
            pred_y_nm=float(pred[0][1]),
            pred_sigma_nm=float(pred[1]),
            offset_x_nm=float(offset[0]),
            offset_y_nm=float(offset[1]),
            wall_s=finished,
            latency_s=finished - started,
            field_json=json.dumps(None if field is None else field.model_dump()),
        )
        return FrameOutcome(
            record=record,
            curve=self.curve,
            curve_dict=None if self.curve is None else self.curve.to_dict(),
            predictor_name=self.predictor.name,
            predictor_state=self.predictor.state_dict() if fed else None,
            field=field,
            reference=reference_image,
            image=image,
            low_confidence=not fed and not paused and reason not in ("reference",),
        )

    # ------------------------------------------------------------------ model

    def _predict(self, t_s: float) -> tuple[npt.NDArray[np.float64], float]:
        """Prediction of p at ``t_s`` from the current model (NaN before any data)."""
        if self.n_fed == 0:
            return np.full(2, np.nan), math.nan
        try:
            pred = self.predictor.predict([t_s], self.history)
        except (ValueError, ArithmeticError) as err:
            log.warning("prediction at t=%.3f s failed: %s", t_s, err)
            return np.full(2, np.nan), math.nan
        mean = np.asarray(pred.mean_nm, dtype=np.float64).reshape(-1, 2)[0]
        sig = np.asarray(pred.sigma_nm, dtype=np.float64).reshape(-1, 2)[0]
        return mean, float(np.hypot(sig[0], sig[1]) / math.sqrt(2.0))

    def _build_curve(self, t_now_s: float) -> OffsetCurve | None:
        """d(t) from now on, continuous in value and slope with the previous curve."""
        from afmdrift.model._reconstruct import reconstruct_offset

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


def _observation(r: FrameRecord) -> Observation:
    from afmdrift.drivers._base import ScanDirection

    return Observation(
        t_s=r.t_mid_s,
        x_nm=r.x_nm,
        y_nm=r.y_nm,
        sigma_nm=r.sigma_nm if math.isfinite(r.sigma_nm) else 0.0,
        direction=ScanDirection(r.direction),
        frame=r.seq,
    )


def _summarise_field(inc: Any, pixel_size_nm: tuple[float, float]) -> FieldSummary | None:
    """Mean, spread and confidence of a DriftResult's valid block vectors (nm)."""
    fld = getattr(inc, "field", None)
    if fld is None:
        return None
    vectors = np.asarray(fld.vectors_px, dtype=np.float64).reshape(-1, 2) * np.asarray(
        pixel_size_nm, dtype=np.float64
    )
    valid = np.asarray(fld.valid, dtype=bool).reshape(-1)
    conf = np.asarray(fld.confidence, dtype=np.float64).reshape(-1)
    good = vectors[valid]

    def stat(values: npt.NDArray[np.float64], fn: Callable[[Any], Any]) -> float | None:
        if values.size == 0:
            return None
        v = float(fn(values))
        return v if math.isfinite(v) else None

    return FieldSummary(
        total_blocks=int(valid.size),
        valid_blocks=int(valid.sum()),
        mean_dx_nm=stat(good[:, 0], np.mean),
        mean_dy_nm=stat(good[:, 1], np.mean),
        std_dx_nm=stat(good[:, 0], np.std),
        std_dy_nm=stat(good[:, 1], np.std),
        median_confidence=stat(conf[valid], np.median),
    )


def process_and_record(
    pipeline: FramePipeline,
    store: RunStore,
    frame: Frame,
    *,
    channels: Sequence[ChannelSample],
    events: Sequence[tuple[int, int, Event]],
    seq: int,
    epoch: int = 0,
    detected_wall_s: float | None = None,
    paused: bool = False,
    t_now_s: float | None = None,
) -> FrameOutcome:
    """One frame, start to finish: history, pipeline, and one store transaction.

    The daemon (in its worker thread) and ``afmdrift replay`` both call this,
    so a replayed session goes through exactly the daemon's code.
    ``events`` are ``(epoch, log_index, Event)`` entries logged since the
    previous frame, ``channels`` the samples read since then.
    """
    pipeline.ingest(channels, [e for _, _, e in events])
    outcome = pipeline.process(
        frame,
        seq=seq,
        epoch=epoch,
        detected_wall_s=detected_wall_s,
        paused=paused,
        t_now_s=t_now_s,
    )
    for sample in channels:
        store.add_channels(sample)
    for ep, idx, e in events:
        store.add_event(epoch=ep, log_index=idx, event=e)
    store.record_frame(
        outcome.record,
        predictor=outcome.predictor_name,
        predictor_state=outcome.predictor_state,
        curve=outcome.curve_dict if outcome.predictor_state is not None else None,
        image=outcome.image,
        reference=outcome.reference,
    )
    return outcome
