"""A session's frames de-warped by its drift trajectory: ``afmdrift correct``."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

from afmdrift.config import AfmdriftConfig
from afmdrift.model import FrameTrajectory
from afmdrift.pipeline import dewarp_frame, image_positions
from afmdrift.records import EventKind
from afmdrift.runs._session import session_pipeline
from afmdrift.session import Session, write_session

__all__ = ["CorrectionSummary", "correct_session"]


@dataclass(frozen=True, slots=True)
class CorrectionSummary:
    """What :func:`correct_session` wrote."""

    out: Path
    frames_written: int
    frames_skipped: list[int]
    mode: str


def correct_session(
    session: Session,
    out: str | Path,
    *,
    config: AfmdriftConfig,
    mode: Literal["smoothed", "causal"] = "smoothed",
    output: Literal["session", "npy"] = "session",
    fill: Literal["nan", "nearest"] = "nearest",
    prior_px: tuple[float, float] | None = None,
) -> CorrectionSummary:
    """De-warp every frame of ``session`` with its drift trajectory.

    The session goes through :class:`FramePipeline` (as ``afmdrift replay``);
    ``mode`` picks the trajectory: ``smoothed`` (the whole session at once,
    every frame has samples) or ``causal`` (what the daemon knew when each
    frame arrived; a reference frame, which has no samples of its own, is
    moved by its position as a whole). Frames that were not measured are
    skipped (their numbers are in the summary). ``output`` is a session
    directory (format v1; the same times, channels and truth, and no
    ``offset_move`` events, since the corrected frames no longer show them)
    or ``DIR/frames.npy`` (N, rows, cols) float32 with ``DIR/frames.csv``
    (frame, t_start_s, t_end_s). ``prior_px``: the expected drift of the
    first frame after the first, px (:func:`session_pipeline`).
    """
    pipeline = session_pipeline(session, config, keep_trajectory=True, prior_px=prior_px)
    causal: dict[int, FrameTrajectory] = {}
    records = []
    for k, outcome in enumerate(pipeline.run(session.iter_frames())):
        records.append(outcome.record)
        if outcome.trajectory is not None:
            causal[k] = outcome.trajectory
    samples = pipeline.positions.trajectory.smoothed() if mode == "smoothed" else causal
    t_ref = pipeline.t_ref_s if pipeline.t_ref_s is not None else 0.0
    images: list[npt.NDArray[np.float32]] = []
    kept: list[int] = []
    skipped: list[int] = []
    for k, frame in enumerate(session.iter_frames()):
        traj = samples.get(k)
        r = records[k]
        if traj is not None:
            t = traj.t_s
            m = image_positions(traj, session.events, t_ref)
        elif r.valid and np.isfinite(r.image_x_nm) and np.isfinite(r.image_y_nm):
            t = np.array([frame.t_mid_s])
            m = np.array([[r.image_x_nm, r.image_y_nm]])
        else:
            skipped.append(k)
            continue
        images.append(dewarp_frame(frame, t, m, fill=fill))
        kept.append(k)
    target = Path(out)
    if output == "npy":
        target.mkdir(parents=True, exist_ok=True)
        stack = np.stack(images) if images else np.zeros((0, *session.frames.shape[1:]), np.float32)
        np.save(target / "frames.npy", stack)
        times = session.frame_times[kept]
        with (target / "frames.csv").open("w", encoding="utf-8") as fh:
            fh.write("frame,t_start_s,t_end_s\n")
            for k, (a, b) in zip(kept, times, strict=True):
                fh.write(f"{k},{a!r},{b!r}\n")
    else:
        meta = dataclasses.replace(
            session.meta,
            source=f"afmdrift correct ({mode} drift trajectory) of: {session.meta.source}",
        )
        corrected = Session(
            meta=meta,
            frames=np.stack(images) if images else np.zeros((0, 1, 1), np.float32),
            frame_times=session.frame_times[kept],
            directions=[session.directions[k] for k in kept],
            channel_t_s=session.channel_t_s,
            channels=dict(session.channels),
            events=[e for e in session.events if e.kind is not EventKind.OFFSET_MOVE],
            truth=session.truth,
        )
        write_session(corrected, target)
    return CorrectionSummary(
        out=target, frames_written=len(kept), frames_skipped=skipped, mode=mode
    )
