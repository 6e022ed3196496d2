"""A stack or movie through the daemon's position component, frame by frame:
what ``afmdrift measure STACK`` prints and ``afmdrift batch`` writes."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from afmdrift.config import AfmdriftConfig, RegistrationConfig
from afmdrift.model import make_predictor
from afmdrift.runs._correct import correct_session
from afmdrift.runs._session import session_pipeline
from afmdrift.session import Session, stack_session

if TYPE_CHECKING:
    from afmdrift.io import AfmImage

__all__ = ["track_session", "track_stack"]


def track_stack(
    frames: Sequence[AfmImage],
    config: AfmdriftConfig | RegistrationConfig,
    *,
    dewarp: Path | None = None,
    prior_px: tuple[float, float] | None = None,
) -> Iterator[dict[str, Any]]:
    """Track a stack or movie through the daemon's position component
    (:class:`afmdrift.pipeline.DriftPositions`: the keyframe policy of
    ``[registration] reference``, the drift trajectory with each block row
    placed at its scan time), frame by frame.

    Frames are timed as ``afmdrift import`` times them
    (:func:`afmdrift.session.session_from_images`, in time order); a file
    without any timing is taken as frames 1 s apart, back to back (positions
    do not depend on it; trajectory times do). Yields one JSON-ready dict per
    frame ``i >= 1``: ``ref_frame`` (the frame it was measured against),
    ``cur_frame``, ``t_s`` (mid-scan time; ``ref_t_s``/``cur_t_s``: scan
    starts since frame 0's, when the file has timestamps), the increment since the previous
    valid frame (``dx_px`` ... as :meth:`DriftResult.to_dict`), and, when
    valid, ``cumulative_{dx,dy}_{px,nm}`` since frame 0 (the drift trajectory
    at the frame's mid-scan time) and ``trajectory`` (its samples: ``t_s``,
    ``x_nm``, ``y_nm``, ``sigma_x_nm``, ``sigma_y_nm``). A frame the engine
    refuses (blank, NaN) gives ``{"valid": false, "error": ...}``. With
    ``dewarp``, the de-warped frames are written there (``frames.npy``,
    ``frames.csv``) once the stack is done.
    """
    cfg = config if isinstance(config, AfmdriftConfig) else AfmdriftConfig(registration=config)
    session, timed = stack_session(frames)
    yield from track_session(session, cfg, timed=timed, dewarp=dewarp, prior_px=prior_px)


def track_session(
    session: Session,
    config: AfmdriftConfig,
    *,
    timed: bool = True,
    dewarp: Path | None = None,
    prior_px: tuple[float, float] | None = None,
) -> Iterator[dict[str, Any]]:
    """:func:`track_stack` on a session already read (a session directory, or
    the images of a stack); ``timed``: whether its frame times are the
    instrument's (``ref_t_s`` and ``cur_t_s`` are reported then). The
    session's event log places each frame's block windows (commanded offset
    moves) as in ``afmdrift replay`` (:func:`session_pipeline`), and
    ``prior_px`` is the expected drift of the first frame after the first."""
    cfg = config
    # Positions do not depend on the model: the model stage is skipped.
    pipeline = session_pipeline(
        session,
        cfg,
        predictor=make_predictor("last_value", cfg.model),
        model=False,
        prior_px=prior_px,
    )
    px, py = session.meta.pixel_size_nm
    for k, outcome in enumerate(pipeline.run(session.iter_frames())):
        if k == 0:
            continue
        r, pos = outcome.record, outcome.position
        ref_frame = None if pos is None else pos.reference_key
        doc: dict[str, Any] = {"ref_frame": ref_frame, "cur_frame": k, "t_s": r.t_mid_s}
        if timed:
            # scan starts since frame 0's, as the file headers give them
            if ref_frame is not None:
                doc["ref_t_s"] = float(session.frame_times[ref_frame, 0])
            doc["cur_t_s"] = r.t_start_s
        if r.reason.startswith("registration failed"):
            doc.update(valid=False, error=r.reason.removeprefix("registration failed: "))
            yield doc
            continue
        if pos is not None and pos.increment is not None:
            doc.update(pos.increment.to_dict())
        valid = r.valid and not r.reason
        doc["valid"] = bool(valid)
        doc["reason"] = r.reason or None
        if valid:
            doc.update(
                cumulative_dx_px=r.image_x_nm / px,
                cumulative_dy_px=r.image_y_nm / py,
                cumulative_dx_nm=r.image_x_nm,
                cumulative_dy_nm=r.image_y_nm,
                sigma_position_nm=r.sigma_nm,
            )
            traj = outcome.trajectory
            if traj is not None:
                doc["trajectory"] = [
                    {
                        "t_s": float(traj.t_s[j]),
                        "x_nm": float(traj.xy_nm[j, 0]),
                        "y_nm": float(traj.xy_nm[j, 1]),
                        "sigma_x_nm": float(traj.sigma_nm[j, 0]),
                        "sigma_y_nm": float(traj.sigma_nm[j, 1]),
                    }
                    for j in range(traj.t_s.size)
                ]
        yield doc
    if dewarp is not None:
        correct_session(session, dewarp, config=cfg, output="npy", fill="nan", prior_px=prior_px)
