"""Record a simulated session (``afmdrift sim record``) as a format-v1 directory.

The simulator runs on its virtual clock as fast as it can. Besides the
format-v1 files (``session.json``, ``frames.npy``/``.csv``, ``channels.csv``,
``events.csv``, ``truth.csv``) the directory holds two extra files that readers
may ignore:

* ``truth_components.csv``: ``t_s`` and ``<effect>_x_nm, <effect>_y_nm`` for
  every drift effect of the scenario's physics (:data:`afmdrift.drivers.sim.COMPONENTS`,
  or ``HEAT_NETWORK_COMPONENTS`` with ``physics.model = "heat_network"``); their
  sum is ``truth.csv``;
* ``scenario.json``: the full validated scenario, with the seed used.

``session.json`` carries ``"simulator": {"scenario", "seed",
"scan_direction_bias_nm"}``. truth.csv holds the drift p(t) only: no commanded
offsets and no scan-direction bias (which is applied per frame, +b/2 on up and
−b/2 on down frames).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import time
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import numpy.typing as npt

from afmdrift.drivers.sim._instrument import SimulatedAFM
from afmdrift.drivers.sim._scenario import Scenario, load_scenario
from afmdrift.records import Frame, ScanDirection
from afmdrift.session import Session, SessionMeta, write_session

__all__ = ["RecordSummary", "drift_statistics", "record_session"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class RecordSummary:
    """What :func:`record_session` wrote and how long it took."""

    path: Path
    frames: int
    duration_s: float
    wall_s: float
    stats: dict[str, float]


def drift_statistics(
    truth: npt.NDArray[np.float64], frame_mid_s: npt.NDArray[np.float64]
) -> dict[str, float]:
    """Summary of a drift record.

    Parameters
    ----------
    truth : ndarray, shape (m, 3)
        ``t_s, x_nm, y_nm`` rows.
    frame_mid_s : ndarray, shape (n,)
        Mid-scan times of the frames.

    Returns
    -------
    dict
        ``mean_speed_nm_per_s`` (mean |Δp|/Δt between frames), ``max_speed_nm_per_s``,
        ``excursion_nm`` (largest |p(t) − p(0)|), ``net_nm`` (|p(end) − p(0)|),
        ``rms_frame_step_nm`` (RMS |Δp| between consecutive frames),
        ``max_frame_step_nm``.
    """
    t, x, y = truth[:, 0], truth[:, 1], truth[:, 2]
    rel = np.hypot(x - x[0], y - y[0])
    out = {"excursion_nm": float(rel.max()), "net_nm": float(rel[-1])}
    if frame_mid_s.size >= 2:
        px = np.interp(frame_mid_s, t, x)
        py = np.interp(frame_mid_s, t, y)
        step = np.hypot(np.diff(px), np.diff(py))
        speed = step / np.diff(frame_mid_s)
        out.update(
            mean_speed_nm_per_s=float(speed.mean()),
            max_speed_nm_per_s=float(speed.max()),
            rms_frame_step_nm=float(np.sqrt(np.mean(step**2))),
            max_frame_step_nm=float(step.max()),
        )
    return out


def record_session(
    scenario: Scenario | str | Path,
    out: str | Path,
    *,
    seed: int | None = None,
    duration_s: float | None = None,
    frames: int | None = None,
) -> RecordSummary:
    """Run a scenario on the virtual clock and write a session directory.

    Parameters
    ----------
    scenario : Scenario, path or built-in name
    out : path
        Session directory (created; existing files are replaced).
    seed : int, optional
        Overrides the scenario's seed.
    duration_s : float, optional
        Virtual time to record, s (default ``scenario.duration_s``).
    frames : int, optional
        Stop after this many frames (and at ``duration_s`` if also given).

    Raises
    ------
    ValueError
        ``duration_s`` or ``frames`` is not positive, or no frame would be recorded.
    """
    wall0 = time.perf_counter()
    if not isinstance(scenario, Scenario):
        scenario = load_scenario(scenario)
    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"duration_s = {duration_s} must be positive")
    if frames is not None and frames < 1:
        raise ValueError(f"frames = {frames} must be >= 1")
    sim = SimulatedAFM(scenario, seed=seed)
    limit_s = float(duration_s) if duration_s is not None else None
    if limit_s is None and frames is None:
        limit_s = scenario.duration_s
    if limit_s is None:
        limit_s = math.inf
    step_s = sim.frame_period_s
    # Frames go straight into one float32 block (half the memory of float64, far
    # finer than the noise), sized by the fixed schedule of a recording.
    g = sim.geometry
    expected = int(max(0.0, (min(limit_s, 1e9) - g.scan_time_s) // g.frame_period_s + 1))
    if frames is not None:
        expected = min(expected, frames)
    block = np.empty((expected, g.pixels[1], g.pixels[0]), dtype=np.float32)
    recorded: list[Frame] = []
    t = 0.0
    while t < limit_s and (frames is None or len(recorded) < frames):
        t = min(t + step_s, limit_s)
        for f in sim.advance_to(t):
            k = len(recorded)
            if k < expected and f.heights_nm.shape == block.shape[1:]:
                block[k] = f.heights_nm
                recorded.append(replace(f, heights_nm=block[k]))
            else:
                recorded.append(replace(f, heights_nm=f.heights_nm.astype(np.float32)))
    if frames is not None and len(recorded) > frames:
        recorded = recorded[:frames]
        t = recorded[-1].t_end_s
    if not recorded:
        raise ValueError(
            f"no frame completed in {limit_s:g} s (frame period {sim.frame_period_s:g} s)"
        )
    t_end = t
    session = _to_session(sim, recorded, t_end, block=block)
    root = write_session(session, out)
    _write_components(sim, root / "truth_components.csv", session.truth)
    doc = scenario.model_dump(mode="json")
    doc["seed"] = sim.seed
    (root / "scenario.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    assert session.truth is not None
    stats = drift_statistics(session.truth, np.array([f.t_mid_s for f in recorded]))
    wall = time.perf_counter() - wall0
    _log.info("recorded %d frames over %.0f s in %.2f s wall", len(recorded), t_end, wall)
    return RecordSummary(
        path=root, frames=len(recorded), duration_s=t_end, wall_s=wall, stats=stats
    )


def _to_session(
    sim: SimulatedAFM, frames: list[Frame], t_end_s: float, *, block: npt.NDArray[np.float32]
) -> Session:
    sensors = sim.scenario.sensors
    ch_t = np.arange(0.0, t_end_s + 1e-9, sensors.record_period_s)
    channels = sim.sensor_series(ch_t)
    tr_t = np.arange(0.0, t_end_s + 1e-9, sensors.truth_period_s)
    p = sim.physics.drift_at(tr_t)
    truth = np.column_stack([tr_t, p])
    shape = frames[0].heights_nm.shape
    if any(f.heights_nm.shape != shape for f in frames):
        raise ValueError("frames of different shapes cannot be stored in one session")
    in_block = len(frames) == block.shape[0] and all(
        np.shares_memory(f.heights_nm, block) for f in frames
    )
    stack = block if in_block else np.stack([f.heights_nm for f in frames])
    up_bias = sim.direction_bias_nm(ScanDirection.UP)
    meta = SessionMeta(
        pixel_size_nm=frames[0].pixel_size_nm,
        line_time_s=1.0 / sim.line_rate_hz,
        start_time=datetime.now(UTC).replace(microsecond=0).isoformat(),
        source=f"afmdrift simulator, scenario {sim.scenario.name!r}, seed {sim.seed}",
        extra={
            "simulator": {
                "scenario": sim.scenario.name,
                "seed": sim.seed,
                "scan_direction_bias_nm": [2.0 * up_bias[0], 2.0 * up_bias[1]],
            }
        },
    )
    return Session(
        meta=meta,
        frames=stack,
        frame_times=np.array([(f.t_start_s, f.t_end_s) for f in frames], dtype=np.float64),
        directions=[f.direction for f in frames],
        channel_t_s=ch_t,
        channels=channels,
        events=sim.events,
        truth=truth,
    )


def _write_components(sim: SimulatedAFM, path: Path, truth: npt.NDArray[np.float64] | None) -> None:
    assert truth is not None
    t = truth[:, 0]
    comps = sim.physics.components_at(t)
    header = ["t_s"] + [f"{c}_{a}_nm" for c in comps for a in "xy"]
    cols = [t] + [comps[c][:, k] for c in comps for k in range(2)]
    data = np.column_stack(cols)
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows([[repr(float(v)) for v in row] for row in data])
    tmp.replace(path)
