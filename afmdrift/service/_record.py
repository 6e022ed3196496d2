"""One frame, start to finish: pipeline, then one store transaction."""

from __future__ import annotations

from collections.abc import Iterable

from afmdrift.pipeline import FrameOutcome, FramePipeline
from afmdrift.records import ChannelSample, Event, Frame, LoggedEvent
from afmdrift.service._store import RunStore

__all__ = ["process_and_record"]


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
    next_frame: Frame | None = None,
) -> FrameOutcome:
    """Process ``frame`` and commit it, with what reached the model's history, at once.

    The daemon (in its worker thread) and ``afmdrift replay`` both call this,
    so a replayed session goes through exactly the daemon's code. ``channels``
    and ``events`` are entries that became known since the previous call; the
    ones logged up to the end of the frame reach the model with it and are
    committed in the frame's transaction, later ones wait for the next frame.
    ``next_frame``: see :meth:`FramePipeline.process` (replay has it; the
    daemon does not).
    """
    pipeline.push(channels, events)
    outcome = pipeline.process(
        frame,
        seq=seq,
        epoch=epoch,
        detected_wall_s=detected_wall_s,
        t_now_s=t_now_s,
        hold=hold,
        next_frame=next_frame,
    )
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
    return outcome
