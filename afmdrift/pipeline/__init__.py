"""The per-frame pipeline: from a frame to a drift position, a prediction and d(t).

Between the model and the service: the daemon, ``afmdrift replay`` and
``afmdrift diagnose`` run every frame through :class:`FramePipeline` (its
stages are listed in :meth:`FramePipeline.process`), and the run store keeps
the :class:`FrameRecord` it produces.
"""

from afmdrift.pipeline._dewarp import dewarp_frame, image_positions
from afmdrift.pipeline._frame import FrameOutcome, FramePipeline
from afmdrift.pipeline._positions import DriftPositions, FramePosition, summarise_field
from afmdrift.pipeline._records import (
    FRAME_COLUMNS,
    MEASUREMENT_COLUMNS,
    FrameRecord,
    ResumeState,
    measurement_row,
    observation_from_record,
    record_from_row,
)
from afmdrift.pipeline._series import (
    CorrectionSummary,
    correct_session,
    measure_session,
    series_from_records,
)
from afmdrift.pipeline._track import track_session, track_stack

__all__ = [
    "FRAME_COLUMNS",
    "MEASUREMENT_COLUMNS",
    "CorrectionSummary",
    "DriftPositions",
    "FrameOutcome",
    "FramePipeline",
    "FramePosition",
    "FrameRecord",
    "ResumeState",
    "correct_session",
    "dewarp_frame",
    "image_positions",
    "measure_session",
    "measurement_row",
    "observation_from_record",
    "record_from_row",
    "series_from_records",
    "summarise_field",
    "track_session",
    "track_stack",
]
