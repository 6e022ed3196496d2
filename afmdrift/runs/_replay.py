"""Replay a recorded session through the daemon's pipeline, as fast as possible.

``afmdrift replay SESSION --out RUN_DIR`` runs every frame of a session
(format v1) through :meth:`FramePipeline.run` and commits each with
:func:`record_outcome`, as the daemon does for each new frame; the session's
channels and events are known from the start, and each reaches the model
with the first frame that ends after it was logged
(:class:`~afmdrift.model.HistoryFeed`). It writes the run store and
``RUN_DIR/measurements.csv``, ``RUN_DIR/trajectory.csv`` (the causal drift
trajectory, as the daemon writes it) and ``RUN_DIR/trajectory_smoothed.csv``
(the same samples from the whole session at once); columns in docs/service.md.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from afmdrift.config import AfmdriftConfig
from afmdrift.errors import InputError
from afmdrift.pipeline import FrameOutcome
from afmdrift.runs._csv import trajectory_rows, write_trajectory_csv
from afmdrift.runs._record import record_outcome
from afmdrift.runs._session import session_pipeline
from afmdrift.runs._store import RunStore
from afmdrift.session import Session, read_session

__all__ = ["MIN_REPLAY_FRAMES", "ReplaySummary", "replay_session"]

#: The fewest frames with a valid measurement that give a prediction error:
#: the first starts the model (nothing predicts it), the second is predicted
#: from it.
MIN_REPLAY_FRAMES = 2


@dataclass(frozen=True, slots=True)
class ReplaySummary:
    """What a replay did (errors are Euclidean prediction errors, nm; NaN
    with fewer than :data:`MIN_REPLAY_FRAMES` valid frames)."""

    run_dir: Path
    measurements_csv: Path
    frames: int
    fed_model: int
    mean_pred_error_nm: float
    max_pred_error_nm: float
    wall_s: float
    #: Frames whose shift the prior alone picked among lattice translations
    #: (``decided_by == "prior"``): only as good as the prior.
    prior_decided: int = 0
    #: Frames with a valid measurement.
    valid_frames: int = 0


def replay_session(
    session: Session | str | Path,
    run_dir: str | Path,
    *,
    config: AfmdriftConfig,
    on_frame: Callable[[int], None] | None = None,
    prior_px: tuple[float, float] | None = None,
) -> ReplaySummary:
    """Run the daemon's per-frame pipeline over ``session`` and record the run.
    ``on_frame`` is given the number of frames done after each frame is
    recorded (a batch worker's progress); ``prior_px`` is the expected drift
    of the first frame after the first, px (:func:`session_pipeline`).

    Raises
    ------
    InputError
        ``run_dir`` already holds a run (replays never mix with other runs), or
        the session cannot be read.
    """
    started = time.perf_counter()
    s = session if isinstance(session, Session) else read_session(session)
    out = Path(run_dir)
    store = RunStore(
        out,
        archive_frames=config.service.archive_frames,
        keep_model_states=config.service.keep_model_states,
    )
    try:
        if store.frame_count():
            raise InputError(
                f"{out}: already holds a run of {store.frame_count()} frames; "
                "replay into an empty directory"
            )
        store.set_meta(
            {
                "source": f"replay:{s.meta.source}",
                "config": config.model_dump_json(),
            }
        )
        pipeline = session_pipeline(s, config, keep_trajectory=True, prior_px=prior_px)
        errors: list[float] = []
        fed = valid = 0
        by_prior = 0
        for done, outcome in enumerate(pipeline.run(s.iter_frames()), start=1):
            record_outcome(store, outcome)
            fed += outcome.record.fed_model
            valid += outcome.record.valid
            by_prior += decided_by_prior(outcome)
            if math.isfinite(outcome.record.pred_error_nm):
                errors.append(outcome.record.pred_error_nm)
            if on_frame is not None:
                on_frame(done)
        csv_path = store.write_measurements_csv(out / "measurements.csv")
        smoothed = pipeline.positions.trajectory.smoothed()
        write_trajectory_csv(
            out / "trajectory_smoothed.csv",
            [row for key, traj in smoothed.items() for row in trajectory_rows(key, traj)],
        )
        n = store.frame_count()
    finally:
        store.close()
    return ReplaySummary(
        run_dir=out,
        measurements_csv=csv_path,
        frames=n,
        fed_model=fed,
        mean_pred_error_nm=statistics.fmean(errors) if errors else math.nan,
        max_pred_error_nm=max(errors) if errors else math.nan,
        wall_s=time.perf_counter() - started,
        prior_decided=by_prior,
        valid_frames=valid,
    )


def decided_by_prior(outcome: FrameOutcome) -> bool:
    """Whether the prior alone picked the frame's shift among lattice
    translations (:attr:`DriftResult.decided_by`)."""
    pos = outcome.position
    inc = None if pos is None else pos.increment
    return bool(inc is not None and inc.valid and inc.decided_by == "prior")
