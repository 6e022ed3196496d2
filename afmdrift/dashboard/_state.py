"""What the dashboard knows about a run, in bounded memory, and its JSON for the page.

:class:`RunState` is fed from two sides: the daemon's ZeroMQ topics (fast:
a ``frame`` message is on the page within a fraction of a second) and the
read-only run store (complete: the prediction's uncertainty, channels, events,
the predictor's state, the history before the dashboard started). A frame is
keyed by its service frame number (``FrameMsg.frame`` = store ``seq``), so the
store's row simply completes the wire's.

Memory is bounded for any run length: frames in a ring of ``max_frames``, the
offset stream and each channel in an :class:`Envelope`, events in a ring,
truth points halved whenever they exceed their cap.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from afmdrift.dashboard._envelope import Envelope
from afmdrift.dashboard._live import change_effect
from afmdrift.pipeline import FrameRecord
from afmdrift.wire import FrameMsg, ModelMsg, OffsetMsg, StatusMsg

__all__ = ["ArrayTruth", "FunctionTruth", "RunState", "TruthSource", "envelope_json"]

#: Truth points drawn between two consecutive frames.
_TRUTH_POINTS_PER_FRAME = 8
#: Truth points kept before they are thinned by half.
_TRUTH_CAP = 8000
#: Events kept (the newest).
_EVENT_CAP = 2000
#: The newest model changes whose error before and after the summary measures.
_CHANGES_MEASURED = 5
#: Channels followed (the first this many names seen).
_CHANNEL_CAP = 32


class TruthSource(Protocol):
    """The true drift p(t) of a simulated or recorded session."""

    @property
    def label(self) -> str:
        """Where it comes from, for the page (e.g. ``"session /data/s1 (truth.csv)"``)."""
        ...

    def at(self, t_s: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """True drift at instrument times ``t_s`` (s): shape (n, 2), (x_nm, y_nm)."""
        ...


@dataclass(frozen=True)
class ArrayTruth:
    """Truth from a table ``(t_s, x_nm, y_nm)`` (a session's ``truth.csv``), linearly
    interpolated."""

    table: npt.NDArray[np.float64]
    label: str

    def at(self, t_s: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        t = np.asarray(t_s, dtype=np.float64)
        x = np.interp(t, self.table[:, 0], self.table[:, 1])
        y = np.interp(t, self.table[:, 0], self.table[:, 2])
        return np.stack([x, y], axis=-1)


@dataclass(frozen=True)
class FunctionTruth:
    """Truth from a callable ``t_s -> (n, 2)`` (an in-process simulator)."""

    function: Callable[[npt.NDArray[np.float64]], npt.NDArray[np.float64]]
    label: str

    def at(self, t_s: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        values: npt.NDArray[np.float64] = np.asarray(
            self.function(np.asarray(t_s, dtype=np.float64)), dtype=np.float64
        )
        return values


def envelope_json(env: Envelope, start: int = 0) -> dict[str, Any]:
    """Bins ``start, ...`` of an envelope as JSON-ready lists.

    ``min``, ``max``, ``last`` hold one list per component, ``flags`` one count
    list per flag; ``generation`` changes when earlier bins were merged (the
    page then replaces everything it holds).
    """
    a = env.arrays(start)
    return {
        "generation": env.generation,
        "start": min(start, env.n_bins),
        "width_s": env.width_s,
        "t_s": [float(v) for v in a["t_s"]],
        "min": [[_num(v) for v in a["min"][:, j]] for j in range(env.components)],
        "max": [[_num(v) for v in a["max"][:, j]] for j in range(env.components)],
        "last": [[_num(v) for v in a["last"][:, j]] for j in range(env.components)],
        "flags": [[int(v) for v in a["flag"][:, j]] for j in range(env.flags)],
        "count": [int(v) for v in a["count"]],
    }


def _num(v: float | None) -> float | None:
    """JSON number: ``None`` for missing or non-finite values."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _frame_from_record(r: FrameRecord) -> dict[str, Any]:
    try:
        field_doc = json.loads(r.field_json) if r.field_json else None
    except ValueError:
        field_doc = None
    return {
        "seq": r.seq,
        "t_s": _num(r.t_mid_s),
        "t_start_s": _num(r.t_start_s),
        "t_end_s": _num(r.t_end_s),
        "x_nm": _num(r.x_nm),
        "y_nm": _num(r.y_nm),
        "dx_nm": _num(r.dx_nm),
        "dy_nm": _num(r.dy_nm),
        "sigma_nm": _num(r.sigma_nm),
        "pred_x_nm": _num(r.pred_x_nm),
        "pred_y_nm": _num(r.pred_y_nm),
        "pred_sigma_nm": _num(r.pred_sigma_nm),
        "pred_error_nm": _num(r.pred_error_nm),
        "valid": r.valid,
        "fed_model": r.fed_model,
        "reason": r.reason,
        "valid_blocks": r.valid_blocks,
        "total_blocks": r.total_blocks,
        "field": field_doc if isinstance(field_doc, dict) else None,
        "direction": r.direction,
        "epoch": r.epoch,
        "rows": r.rows,
        "cols": r.cols,
        "pixel_x_nm": _num(r.pixel_x_nm),
        "pixel_y_nm": _num(r.pixel_y_nm),
        "wall_s": _num(r.wall_s),
        "latency_s": _num(r.latency_s),
        "stored": True,
    }


def _frame_from_msg(m: FrameMsg) -> dict[str, Any]:
    return {
        "seq": m.frame,
        "t_s": _num(m.t_s),
        "x_nm": _num(m.x_nm),
        "y_nm": _num(m.y_nm),
        "dx_nm": _num(m.dx_nm),
        "dy_nm": _num(m.dy_nm),
        "sigma_nm": _num(m.sigma_nm),
        "pred_x_nm": _num(m.pred_x_nm),
        "pred_y_nm": _num(m.pred_y_nm),
        "pred_sigma_nm": None,
        "pred_error_nm": _num(m.pred_error_nm),
        "valid": m.valid,
        "fed_model": m.fed_model,
        "reason": m.reason,
        "valid_blocks": m.valid_blocks,
        "total_blocks": m.total_blocks,
        "field": None if m.field is None else m.field.model_dump(),
        "wall_s": _num(m.wall_s),
        "latency_s": _num(m.latency_s),
        "stored": False,
    }


@dataclass
class _Link:
    """What the dashboard has heard from the daemon's PUB socket."""

    endpoint: str | None
    last_wall_s: float | None = None
    received: int = 0
    rejected: int = 0
    last_error: str = ""
    by_topic: dict[str, int] = field(
        default_factory=lambda: {"offset": 0, "model": 0, "frame": 0, "status": 0}
    )


class RunState:
    """Bounded state of one run, updated from the wire and the store.

    Parameters
    ----------
    max_frames : int
        Frames kept (the newest); older ones stay in the run store.
    rolling_window : int
        Frames in the rolling mean of the one-step prediction error (the
        daemon's ``status.rolling_window`` replaces it once heard).
    offset_capacity : int
        Bins of the offset envelope (see :class:`Envelope`).
    truth : TruthSource, optional
        True drift, drawn shifted so that it is 0 over the reference frame
        (where the measured drift position is 0 by definition).
    """

    def __init__(
        self,
        *,
        max_frames: int = 5000,
        rolling_window: int = 10,
        offset_capacity: int = 2048,
        truth: TruthSource | None = None,
        pub_endpoint: str | None = None,
    ) -> None:
        if max_frames < 10:
            raise ValueError(f"max_frames must be >= 10, got {max_frames}")
        self.max_frames = max_frames
        self.rolling_window = rolling_window
        self.frames: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self.frames_dropped = 0
        self.offsets = Envelope(components=2, flags=2, capacity=offset_capacity)
        self.last_offset: dict[str, Any] | None = None
        #: Where the offset envelope came from when not from the live stream.
        self.offset_source: str | None = None
        self.channels: dict[str, Envelope] = {}
        self.events: deque[dict[str, Any]] = deque(maxlen=_EVENT_CAP)
        self.events_total = 0
        self.status: dict[str, Any] | None = None
        self.predictor: str | None = None
        self.model_info: dict[str, Any] = {}
        self.model_wall_s: float | None = None
        self.link = _Link(endpoint=pub_endpoint)
        self.meta: dict[str, str] = {}
        self.truth = truth
        self.truth_points: list[tuple[float, float, float]] = []
        self._truth_ref: npt.NDArray[np.float64] | None = None
        self._truth_last_t: float | None = None
        self.reference: dict[str, Any] | None = None
        self.diagnosis: dict[str, Any] | None = None
        self.diagnosis_note = ""
        #: The daemon's newest live diagnosis (:func:`~afmdrift.dashboard._live.live_finding`).
        self.live_diagnosis: dict[str, Any] | None = None
        #: Whether the page may add a term, and why not (the dashboard sets it).
        self.control: dict[str, Any] = {"enabled": False, "reason": ""}
        #: The run's model changes (``add_term``, ``remove_term``, ``reload_model``).
        self.model_changes: list[dict[str, Any]] = []
        self.frame_view: dict[str, Any] | None = None
        self.store_note = ""
        #: The run store: "" (none followed), "waiting" (not there yet), "open", "error".
        self.store_state = ""
        #: Its path (``RUN_DIR/run.sqlite``), when a run directory is followed.
        self.store_path: str | None = None
        # Truth points not yet sent to the pages; a reset resends them all.
        self._pending_truth: list[tuple[float, float, float]] = []
        self._truth_reset = False

    # ------------------------------------------------------------------ frames

    def _upsert(self, row: dict[str, Any]) -> dict[str, Any]:
        seq = int(row["seq"])
        old = self.frames.get(seq)
        if old is not None:
            merged = dict(old)
            for k, v in row.items():
                if v is not None or k not in merged:
                    merged[k] = v
            row = merged
        is_new = old is None
        newest = next(reversed(self.frames)) if self.frames else None
        self.frames[seq] = row
        if is_new and newest is not None and seq < newest:
            # Out of order (a store row older than the newest wire frame): re-sort.
            self.frames = OrderedDict(sorted(self.frames.items()))
        while len(self.frames) > self.max_frames:
            self.frames.popitem(last=False)
            self.frames_dropped += 1
        row["roll_error_nm"] = self._rolling_error(seq)
        if row.get("reason") == "reference" and self.reference is None:
            self.set_reference(row)
        if is_new:
            self._add_truth_for(row)
        return row

    def _rolling_error(self, seq: int) -> float | None:
        errors: list[float] = []
        for s in reversed(self.frames):
            if s > seq:
                continue
            e = self.frames[s].get("pred_error_nm")
            if e is not None:
                errors.append(e)
                if len(errors) >= self.rolling_window:
                    break
        return statistics.fmean(errors) if errors else None

    def add_frame_msg(self, msg: FrameMsg) -> dict[str, Any]:
        """A ``frame`` message; returns the frame's row as sent to the page."""
        self._count("frame")
        return self._upsert(_frame_from_msg(msg))

    def add_records(self, records: Iterable[FrameRecord]) -> list[dict[str, Any]]:
        """Store rows (complete the wire's); returns the rows as sent to the page."""
        return [self._upsert(_frame_from_record(r)) for r in records]

    def set_reference(self, row: dict[str, Any]) -> None:
        """The session reference frame (drift position 0): aligns the truth."""
        self.reference = {k: row.get(k) for k in ("seq", "t_s", "t_start_s", "t_end_s") if k in row}
        if self.truth is not None and self._truth_ref is None:
            t_mid = row.get("t_s")
            t0, t1 = row.get("t_start_s"), row.get("t_end_s")
            if t0 is not None and t1 is not None and t1 > t0:
                grid = np.linspace(t0, t1, 64)
            elif t_mid is not None:
                grid = np.array([t_mid], dtype=np.float64)
            else:
                return
            self._truth_ref = np.nanmean(self.truth.at(grid), axis=0)
            # Truth points of frames seen before the reference: recompute.
            times = sorted(r["t_s"] for r in self.frames.values() if r.get("t_s") is not None)
            self.truth_points = []
            self._pending_truth = []
            self._truth_last_t = None
            for t in times:
                self._add_truth_at(t)
            self._truth_reset = True

    def _add_truth_for(self, row: dict[str, Any]) -> None:
        t = row.get("t_s")
        if self.truth is None or self._truth_ref is None or t is None:
            return
        self._add_truth_at(float(t))

    def _add_truth_at(self, t_s: float) -> None:
        assert self.truth is not None
        assert self._truth_ref is not None
        last = self._truth_last_t
        if last is not None and t_s <= last:
            return
        if last is None:
            grid = np.array([t_s])
        else:
            grid = np.linspace(last, t_s, _TRUTH_POINTS_PER_FRAME + 1)[1:]
        values = self.truth.at(grid) - self._truth_ref
        new = [(float(t), float(v[0]), float(v[1])) for t, v in zip(grid, values, strict=True)]
        self.truth_points.extend(new)
        self._pending_truth.extend(new)
        self._truth_last_t = t_s
        if len(self.truth_points) > _TRUTH_CAP:
            self.truth_points = self.truth_points[::2]

    def take_new_truth(self) -> tuple[bool, list[list[float | None]]]:
        """Truth points added since the last call for the pages, and whether they
        replace (True) or extend (False) the points the pages hold."""
        reset = self._truth_reset
        points = self.truth_points if reset else self._pending_truth
        out = [[t, _num(x), _num(y)] for t, x, y in points]
        self._pending_truth = []
        self._truth_reset = False
        return reset, out

    # ------------------------------------------------------------------ wire

    def _count(self, topic: str) -> None:
        # Arrival time on this machine's clock: how long ago the daemon was heard.
        self.link.received += 1
        self.link.by_topic[topic] = self.link.by_topic.get(topic, 0) + 1
        self.link.last_wall_s = time.time()

    def add_offset(self, msg: OffsetMsg) -> None:
        """An ``offset`` sample: into the envelope (invalid and clamped counted per bin)."""
        self._count("offset")
        self.offsets.add(msg.t_s, (msg.x_nm, msg.y_nm), (not msg.valid, msg.clamped))
        self.last_offset = {
            "t_s": msg.t_s,
            "x_nm": _num(msg.x_nm),
            "y_nm": _num(msg.y_nm),
            "valid": msg.valid,
            "clamped": msg.clamped,
            "wall_s": msg.wall_s,
        }

    def add_status(self, msg: StatusMsg) -> None:
        self._count("status")
        self.status = msg.model_dump()
        if msg.rolling_window > 0:
            self.rolling_window = msg.rolling_window

    def add_model(self, msg: ModelMsg) -> None:
        self._count("model")
        self.predictor = msg.predictor
        self.model_wall_s = msg.wall_s

    def add_live_diagnosis(self, finding: dict[str, Any]) -> None:
        """A live diagnosis (from the wire or the run directory); the newest is kept."""
        old = self.live_diagnosis
        if old is None or finding["wall_s"] > old["wall_s"]:
            self.live_diagnosis = finding

    def set_model_changes(self, changes: list[dict[str, Any]]) -> None:
        """The run's model changes, oldest first (each with ``seq``, ``t_s``,
        ``command``, ``term``, ``terms_before``, ``terms_after``)."""
        self.model_changes = changes

    def _changes_json(self) -> list[dict[str, Any]]:
        """The model changes, the newest few with their error before and after."""
        rows = list(self.frames.values())
        out = []
        for k, change in enumerate(self.model_changes):
            effect = None
            if k >= len(self.model_changes) - _CHANGES_MEASURED:
                effect = change_effect(rows, int(change["seq"]))
            out.append(change | {"effect": effect})
        return out

    def wire_rejected(self, error: str) -> None:
        self.link.rejected += 1
        self.link.last_error = error

    # ------------------------------------------------------------------ store

    def add_channels(self, rows: Iterable[tuple[int, float, str, float]]) -> None:
        for _, t_s, name, value in rows:
            env = self.channels.get(name)
            if env is None:
                if len(self.channels) >= _CHANNEL_CAP:
                    continue
                env = self.channels[name] = Envelope(
                    components=1, capacity=1024, initial_width_s=1.0
                )
            env.add(t_s, (value,))

    def add_events(self, rows: Iterable[tuple[int, int, float, str, float, float]]) -> list[Any]:
        new = []
        for _, epoch, t_s, kind, x_nm, y_nm in rows:
            ev = {"t_s": t_s, "kind": kind, "x_nm": x_nm, "y_nm": y_nm, "epoch": epoch}
            self.events.append(ev)
            self.events_total += 1
            new.append(ev)
        return new

    def set_model_state(self, predictor: str, state: dict[str, Any]) -> None:
        """The predictor's stored state after the newest fed frame: its effects."""
        self.predictor = self.predictor or predictor
        info: dict[str, Any] = {"predictor": predictor}
        cfg = state.get("config")
        if isinstance(cfg, dict) and isinstance(cfg.get("terms"), list):
            info["terms"] = [str(t) for t in cfg["terms"]]
        if isinstance(state.get("active"), list):
            info["active"] = [str(t) for t in state["active"]]
        params = state.get("params")
        if isinstance(params, dict):
            info["params"] = {
                str(k): _num(v) for k, v in params.items() if isinstance(v, int | float)
            }
        self.model_info = info

    # ------------------------------------------------------------------ summaries

    def error_trend(self) -> dict[str, Any] | None:
        """Least-squares slope of the one-step prediction error over the last
        3 × rolling-window frames, nm per hour of instrument time."""
        pts = [
            (r["t_s"], r["pred_error_nm"])
            for r in self.frames.values()
            if r.get("pred_error_nm") is not None and r.get("t_s") is not None
        ][-3 * max(self.rolling_window, 2) :]
        if len(pts) < 4:
            return None
        t = np.array([p[0] for p in pts])
        e = np.array([p[1] for p in pts])
        if np.ptp(t) <= 0:
            return None
        slope, _ = np.polyfit(t - t[0], e, 1)
        per_h = float(slope) * 3600.0
        mean = float(np.mean(e))
        # "worse"/"better" when the fitted change over the window exceeds a
        # quarter of the mean error; otherwise "steady".
        change = float(slope) * float(np.ptp(t))
        word = "steady"
        if abs(change) > 0.25 * max(mean, 1e-12):
            word = "getting worse" if change > 0 else "getting better"
        return {"nm_per_h": per_h, "frames": len(pts), "word": word, "mean_nm": mean}

    def offset_json(self, start: int = 0) -> dict[str, Any]:
        """Offset envelope bins from ``start`` for the page (flags: invalid, clamped)."""
        return envelope_json(self.offsets, start)

    def channels_json(self, starts: dict[str, int] | None = None) -> dict[str, Any]:
        """Channel envelopes for the page, each from ``starts[name]`` (default 0)."""
        starts = starts or {}
        return {
            name: envelope_json(env, starts.get(name, 0)) for name, env in self.channels.items()
        }

    def summary(self, *, now_wall_s: float, silent_after_s: float) -> dict[str, Any]:
        """Everything that is not a series: service state, link, model, notes."""
        link = self.link
        age = None if link.last_wall_s is None else now_wall_s - link.last_wall_s
        if link.endpoint is None:
            link_state = "not following a daemon (finished run)"
        elif link.last_wall_s is None:
            link_state = f"waiting for the daemon on {link.endpoint}"
        elif age is not None and age > silent_after_s:
            link_state = f"daemon silent for {age:.0f} s on {link.endpoint}"
        else:
            link_state = f"live from {link.endpoint}"
        latest = next(reversed(self.frames.values())) if self.frames else None
        return {
            "link": {
                "endpoint": link.endpoint,
                "state": link_state,
                "live": link.endpoint is not None and age is not None and age <= silent_after_s,
                "age_s": age,
                "received": link.received,
                "rejected": link.rejected,
                "last_error": link.last_error,
                "by_topic": dict(link.by_topic),
            },
            "status": self.status,
            "offset_source": self.offset_source,
            "predictor": self.predictor,
            "model": self.model_info,
            "trend": self.error_trend(),
            "rolling_window": self.rolling_window,
            "frames_kept": len(self.frames),
            "max_frames": self.max_frames,
            "frames_dropped": self.frames_dropped,
            "latest_frame": latest,
            "last_offset": self.last_offset,
            "offset_samples": self.offsets.samples,
            "events_total": self.events_total,
            "truth": None if self.truth is None else self.truth.label,
            "truth_aligned": self._truth_ref is not None,
            "diagnosis": self.diagnosis,
            "diagnosis_note": self.diagnosis_note,
            "live_diagnosis": self.live_diagnosis,
            "control": self.control,
            "model_changes": self._changes_json(),
            "store_note": self.store_note,
            "store_state": self.store_state,
            "store_path": self.store_path,
            "meta": {k: v for k, v in self.meta.items() if k != "config"},
        }

    def snapshot(self, *, now_wall_s: float, silent_after_s: float) -> dict[str, Any]:
        """The whole state, for a page that just connected."""
        return {
            "type": "snapshot",
            "frames": list(self.frames.values()),
            "truth": [[t, _num(x), _num(y)] for t, x, y in self.truth_points],
            "offset": self.offset_json(0),
            "channels": self.channels_json(),
            "events": list(self.events),
            "frame_view": self.frame_view,
            "summary": self.summary(now_wall_s=now_wall_s, silent_after_s=silent_after_s),
        }
