"""Inputs beside the wire and the store: truth, the diagnose result, frame images.

Truth
    A session directory (``--session``) with ``truth.csv`` (simulated or
    calibrated sessions, ``docs/session-format.md``), or a callable given by an
    in-process simulator (``afmdrift demo``). The run store does not say where
    a replay's session is (its ``source`` meta is the session's own description),
    so the session is named explicitly, as for ``afmdrift diagnose --session``.
Diagnosis
    ``afmdrift diagnose RUN_DIR --json`` prints the documented JSON object
    (``docs/diagnostics.md``) and stores nothing; the dashboard reads it from
    ``RUN_DIR/diagnosis.json`` (or ``--diagnosis FILE``) and re-reads it when the
    file changes.
Frame view
    Per-block vectors are neither published nor stored, only their summary.
    When the frame images exist (``[service] archive_frames = true`` keeps
    ``frames/NNNNNN.npy``; a replay's session has them too), the latest frame is
    measured again against the previous accepted frame with
    :func:`afmdrift.registration.measure_drift`, the engine the daemon uses, and
    shown as re-measured: the daemon searched around its prediction, this
    search starts from the whole-image alignment, so the two can differ.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.config import AfmdriftConfig
from afmdrift.dashboard._state import ArrayTruth
from afmdrift.dashboard._store import DashboardError
from afmdrift.errors import AfmdriftError
from afmdrift.session import read_session

__all__ = ["DiagnosisFile", "FrameImages", "frame_view", "load_session"]

#: Longest edge of the gradient image sent to the page, px.
_VIEW_EDGE_PX = 160


def load_session(session_dir: str | Path) -> tuple[Any, ArrayTruth | None]:
    """The session a run came from and its truth (``None`` without ``truth.csv``).

    Raises
    ------
    DashboardError
        ``session_dir`` is not a readable session.
    """
    try:
        session = read_session(session_dir)
    except AfmdriftError as err:
        raise DashboardError(f"--session {session_dir}: {err}") from None
    if session.truth is None:
        return session, None
    truth = ArrayTruth(
        table=np.asarray(session.truth, dtype=np.float64),
        label=f"session {session_dir} (truth.csv)",
    )
    return session, truth


class DiagnosisFile:
    """A diagnose JSON result, re-read when its modification time changes."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._mtime_ns: int | None = None
        self.result: dict[str, Any] | None = None
        self.note = f"no diagnose result ({path} does not exist)"

    def poll(self) -> bool:
        """Re-read the file if it changed; True when the result or note changed."""
        try:
            mtime = self.path.stat().st_mtime_ns
        except OSError:
            if self._mtime_ns is None and self.result is None:
                return False
            self._mtime_ns, self.result = None, None
            self.note = f"no diagnose result ({self.path} does not exist)"
            return True
        if mtime == self._mtime_ns:
            return False
        self._mtime_ns = mtime
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            self.result = None
            self.note = f"{self.path}: not readable as JSON ({err})"
            return True
        if not isinstance(doc, dict) or not isinstance(doc.get("finding"), str):
            self.result = None
            self.note = f"{self.path}: not an afmdrift diagnose result (no 'finding')"
            return True
        keep = (
            "finding",
            "config",
            "model_effects",
            "active_effects",
            "rmse_nm",
            "peak_error_nm",
            "frames",
            "after",
            "patterns",
        )
        self.result = {k: doc.get(k) for k in keep}
        self.note = f"from {self.path}"
        return True


@dataclass
class FrameImages:
    """Where frame images of a run can be found.

    Parameters
    ----------
    run_dir : Path, optional
        Run directory; ``frames/NNNNNN.npy`` when the run archives frames.
    session : Session, optional
        The session a replay ran over (``seq`` is the session's frame index).
    """

    run_dir: Path | None
    session: Any = None

    def load(self, seq: int) -> npt.NDArray[np.float32] | None:
        """Heights (nm) of frame ``seq``, or ``None`` when not kept."""
        if self.run_dir is not None:
            path = self.run_dir / "frames" / f"{seq:06d}.npy"
            if path.is_file():
                try:
                    return np.asarray(np.load(path, allow_pickle=False), dtype=np.float32)
                except (OSError, ValueError):
                    return None
        if self.session is not None and 0 <= seq < len(self.session):
            heights = self.session.frame(seq).heights_nm
            return np.asarray(heights, dtype=np.float32)
        return None

    def unavailable_reason(self) -> str:
        if self.session is not None:
            return "the session given with --session has no image for this frame"
        return (
            "this run does not archive its frames ([service] archive_frames = false) and no "
            "--session was given, so the block vectors cannot be shown; the daemon publishes "
            "only their summary (below)"
        )


def _block_mean(image: npt.NDArray[np.float64], factor: int) -> npt.NDArray[np.float64]:
    rows, cols = (image.shape[0] // factor) * factor, (image.shape[1] // factor) * factor
    trimmed = image[:rows, :cols]
    means: npt.NDArray[np.float64] = trimmed.reshape(
        rows // factor, factor, cols // factor, factor
    ).mean(axis=(1, 3))
    return means


def frame_view(
    current: npt.NDArray[np.float32],
    reference: npt.NDArray[np.float32],
    *,
    seq: int,
    reference_seq: int,
    pixel_size_nm: tuple[float, float],
    config: AfmdriftConfig,
) -> dict[str, Any]:
    """Gradient image of ``current`` and its block vectors re-measured against ``reference``.

    Returns
    -------
    dict
        JSON-ready: ``seq``, ``reference_seq``, ``z`` (x-gradient of the heights,
        nm per px, block-averaged to at most 160 px per edge, as rows), ``scale``
        (image px per ``z`` px), ``clim`` (1st and 99th percentiles),
        ``centres_px``, ``vectors_px``, ``valid``, ``measured``, ``gain`` (arrow
        length per px of motion), and the re-measured ``result``
        (``DriftResult.to_dict()``).
    """
    # Imported here: the registration engine (FFTW plans, compiled kernels,
    # about 120 MiB) loads only once a frame is actually re-measured.
    from afmdrift.registration import measure_drift

    try:
        result = measure_drift(
            reference, current, pixel_size_nm=pixel_size_nm, config=config.registration
        )
    except AfmdriftError as err:
        return {"seq": seq, "reference_seq": reference_seq, "error": str(err)}
    grad = np.diff(np.asarray(current, dtype=np.float64), axis=1)
    factor = max(1, math.ceil(max(grad.shape) / _VIEW_EDGE_PX))
    small = _block_mean(grad, factor) if factor > 1 else grad
    lo, hi = np.percentile(small, [1, 99])
    f = result.field
    centres = np.asarray(f.centres_px, dtype=np.float64)
    vectors = np.asarray(f.vectors_px, dtype=np.float64)
    measured = np.asarray(f.measured, dtype=bool)
    lengths = np.hypot(vectors[measured, 0], vectors[measured, 1])
    typical = float(np.median(lengths)) if lengths.size else 0.0
    gain = max(1.0, 0.08 * min(current.shape) / typical) if typical > 0 else 1.0

    def nums(a: npt.NDArray[np.float64]) -> list[list[float | None]]:
        return [[float(v) if math.isfinite(v) else None for v in row] for row in a]

    return {
        "seq": seq,
        "reference_seq": reference_seq,
        "z": [[round(float(v), 5) for v in row] for row in small],
        "scale": factor,
        "shape": [int(current.shape[0]), int(current.shape[1])],
        "clim": [float(lo), float(hi)],
        "centres_px": nums(centres),
        "vectors_px": nums(vectors),
        "valid": [bool(v) for v in f.valid],
        "measured": [bool(v) for v in measured],
        "gain": gain,
        "result": result.to_dict(),
    }
