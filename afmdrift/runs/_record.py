"""One frame, start to finish: pipeline, then one store transaction."""

from __future__ import annotations

from collections.abc import Iterable

from afmdrift.pipeline import FrameOutcome, FramePipeline
from afmdrift.records import ChannelSample, Event, Frame, LoggedEvent
from afmdrift.runs._store import RunStore

__all__ = ["process_and_record", "record_outcome"]


def process_and_record(
    pipeline: FramePipeline,
    store: RunStore,
    frame: Frame,
    *,
    channels: Iterable[ChannelSample] = (),
    events: Iterable[Event | LoggedEvent] = (),
    seq: int,
    epoch: int = 0,
    detected_wall_s: float | None = None,
    t_now_s: float | None = None,
    hold: str | None = None,
) -> FrameOutcome:
    """Process ``frame`` and commit it, with what reached the model's history, at once.

    The daemon calls this in its worker thread for each new frame.
    ``channels`` and ``events`` are entries that became known since the
    previous call; the ones logged up to the end of the frame reach the model
    with it and are committed in the frame's transaction, later ones wait for
    the next frame.
    """
    pipeline.push(channels, events)
    outcome = pipeline.process(
        frame,
        seq=seq,
        epoch=epoch,
        detected_wall_s=detected_wall_s,
        t_now_s=t_now_s,
        hold=hold,
    )
    record_outcome(store, outcome)
    return outcome


def record_outcome(store: RunStore, outcome: FrameOutcome) -> None:
    """Commit a processed frame with what reached the model's history with it.

    :func:`process_and_record` (the daemon) and ``afmdrift replay`` (over
    :meth:`FramePipeline.run`) both end each frame here, so a replayed
    session is recorded exactly as the daemon records it.
    """
    for sample in outcome.history.channels:
        store.add_channels(sample)
    for ep, idx, e in outcome.history.events:
        store.add_event(epoch=ep, log_index=idx, event=e)
    store.record_frame(
        outcome.record,
        predictor=outcome.predictor_name,
        predictor_state=outcome.predictor_state,
        curve=outcome.curve_dict if outcome.predictor_state is not None else None,
        image=outcome.image,
        reference=outcome.reference,
        trajectory=outcome.trajectory,
        corrected=outcome.corrected,
    )
