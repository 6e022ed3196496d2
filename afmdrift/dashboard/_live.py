"""Closing the loop on the page: the daemon's live diagnosis, and what a model change did.

The daemon diagnoses its run as it grows (``docs/service.md``, *Live
diagnosis*): each result is a ``diagnosis`` message on the wire and a line of
``RUN_DIR/diagnoses.jsonl``. :class:`LiveDiagnoses` reads the file (for a
page opened after a diagnosis, or a dashboard that is not following the
wire); :func:`live_finding` turns a message into what the panel shows: the
finding in plain words, the candidate to add with its ``term``, and the
logged channel that drives it (the evidence plot draws the one-step errors
beside that channel).

:func:`change_effect` is the panel's "before and after": the RMS of the
one-step prediction errors over the n frames after a model change and the n
frames before it, n growing with the frames after it (up to ``max_frames``),
so the two are always over equal numbers of frames.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from afmdrift.errors import AfmdriftError
from afmdrift.model import make_term
from afmdrift.service import DIAGNOSES_FILE, last_diagnosis
from afmdrift.wire import DiagnosisMsg

__all__ = ["LiveDiagnoses", "change_effect", "live_finding"]

#: Frames on each side of a model change the before/after comparison grows to.
CHANGE_FRAMES = 20


def _driver_channel(candidate: Mapping[str, Any]) -> str | None:
    """The logged channel a candidate responds to (a generic ``channel:`` term's,
    or a library term's own), or None."""
    params = candidate.get("params") or {}
    channel = params.get("channel")
    if isinstance(channel, str):
        return channel
    try:
        term = make_term(str(candidate.get("term", "")))
    except (AfmdriftError, ValueError):
        return None
    named = getattr(term, "channel", None)
    return named if isinstance(named, str) else None


def live_finding(msg: DiagnosisMsg) -> dict[str, Any]:
    """What the diagnosis panel shows of one live diagnosis (JSON-ready).

    ``candidate`` is the leading significant candidate (its ``term`` is what
    "Add to model" sends), or None when nothing is missing.
    """
    doc = msg.diagnosis
    candidates = doc.get("candidates") or []
    top = next((c for c in candidates if isinstance(c, dict) and c.get("significant")), None)
    candidate = None
    if top is not None:
        candidate = {
            "term": top.get("term"),
            "effect": top.get("effect"),
            "family": top.get("family"),
            "evidence": top.get("evidence"),
            "rmse_base_nm": top.get("rmse_base_nm"),
            "rmse_after_nm": top.get("rmse_after_nm"),
            "channel": _driver_channel(top),
        }
    thresholds = doc.get("thresholds") or {}
    return {
        "look": msg.look,
        "reason": msg.reason,
        "first_frame": msg.first_frame,
        "last_frame": msg.last_frame,
        "wall_s": msg.wall_s,
        "duration_s": msg.duration_s,
        "plain_finding": doc.get("plain_finding") or "",
        "finding": doc.get("finding") or "",
        "model_effects": doc.get("model_effects") or [],
        "rmse_nm": doc.get("rmse_nm"),
        "alpha": thresholds.get("alpha"),
        "run_alpha": thresholds.get("run_alpha"),
        "candidate": candidate,
    }


class LiveDiagnoses:
    """The newest diagnosis in ``RUN_DIR/diagnoses.jsonl``, re-read when the file changes."""

    def __init__(self, run_dir: Path) -> None:
        self.path = run_dir / DIAGNOSES_FILE
        self._stamp: tuple[int, int] | None = None
        self.latest: DiagnosisMsg | None = None

    def poll(self) -> bool:
        """Re-read the file if it changed; True when a newer diagnosis was found."""
        try:
            st = self.path.stat()
        except OSError:
            return False
        stamp = (st.st_mtime_ns, st.st_size)
        if stamp == self._stamp:
            return False
        self._stamp = stamp
        found = last_diagnosis(self.path.parent)
        if found is None or (self.latest is not None and found.wall_s <= self.latest.wall_s):
            return False
        self.latest = found
        return True


def change_effect(
    rows: Sequence[Mapping[str, Any]], change_seq: int, *, max_frames: int = CHANGE_FRAMES
) -> dict[str, Any] | None:
    """One-step error RMS before and after a model change, over equal numbers of frames.

    Parameters
    ----------
    rows : sequence of mapping
        Frame rows in frame order, each with ``seq`` and ``pred_error_nm``
        (None where no prediction was made).
    change_seq : int
        The last frame before the change (``ModelChange.seq``): frames after
        it were predicted by the new model.
    max_frames : int
        At most this many frames on each side.

    Returns
    -------
    dict or None
        ``frames`` (n on each side), ``before_rms_nm``, ``after_rms_nm``,
        ``ratio`` (after / before; None when before is 0); None until a frame
        after the change has an error.
    """
    before = [
        float(r["pred_error_nm"])
        for r in rows
        if r["seq"] <= change_seq and r.get("pred_error_nm") is not None
    ]
    after = [
        float(r["pred_error_nm"])
        for r in rows
        if r["seq"] > change_seq and r.get("pred_error_nm") is not None
    ]
    n = min(len(after), len(before), max_frames)
    if n == 0:
        return None
    b = math.sqrt(sum(e * e for e in before[-n:]) / n)
    a = math.sqrt(sum(e * e for e in after[:n]) / n)
    return {
        "frames": n,
        "before_rms_nm": b,
        "after_rms_nm": a,
        "ratio": a / b if b > 0 else None,
    }
