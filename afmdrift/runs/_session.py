"""The one way a recorded session enters the per-frame pipeline."""

from __future__ import annotations

from afmdrift.config import AfmdriftConfig
from afmdrift.model import Predictor
from afmdrift.pipeline import FramePipeline
from afmdrift.session import Session, session_prior_px

__all__ = ["session_pipeline"]


def session_pipeline(
    session: Session,
    config: AfmdriftConfig,
    *,
    predictor: Predictor | None = None,
    keep_trajectory: bool = False,
    model: bool = True,
    prior_px: tuple[float, float] | None = None,
) -> FramePipeline:
    """A :class:`FramePipeline` for ``session`` with everything its logs say
    known from the start: its channels and events (the commanded offset moves
    among them, which place the block windows where the content went), each
    reaching the model with the first frame that ends after it was logged.

    ``prior_px`` is the expected drift (px) of the first frame after the
    first (``--prior-px``); default: the one ``afmdrift import --prior-px``
    stored with the session (:func:`session_prior_px`), if any.

    ``afmdrift replay``, ``evaluate``, ``diagnose``, ``correct``, ``measure
    STACK`` and ``batch`` all start a session here, so a track never differs
    from a replay because one of them forgot the event log or the prior.
    """
    pipeline = FramePipeline(
        config=config,
        predictor=predictor,
        keep_trajectory=keep_trajectory,
        model=model,
        first_prior_px=prior_px if prior_px is not None else session_prior_px(session),
    )
    pipeline.push(session.channel_samples(), session.events)
    return pipeline
