"""Closed loop on the Nanonis simulator: 2 simulated hours of the default scenario.

Two actuators, each over the Nanonis protocol on loopback TCP: the scan frame
(``Scan.FrameSet``) and the controller's own drift compensation
(``Piezo.DriftCompSet``, piecewise-constant velocities from d(t)). Ground truth
comes from the simulator (never sent over the wire): where image content sits
at each frame's mid-time, ``p(t) − c(t) − q(t)`` (drift minus commanded offset
minus the compensation ramp), relative to the first frame.
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import numpy as np
import pytest
import zmq.asyncio

from afmdrift.drivers.sim import SCENARIO_DIR, SimulatedAFM
from afmdrift.service import RunStore

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from service_sim import nanonis_closed_loop

# 2.5 min of wall time per actuator: excluded by default, run with -m soak.
pytestmark = [pytest.mark.asyncio, pytest.mark.slow, pytest.mark.soak]

DURATION_S = 7200.0
SPEED = 50.0


async def _closed_loop(run_dir: Path, actuator: str) -> dict[str, float]:
    sim = SimulatedAFM.from_scenario(SCENARIO_DIR / "default.toml")
    ctx = zmq.asyncio.Context()
    try:
        async with nanonis_closed_loop(sim, run_dir, ctx, speed=SPEED, actuator=actuator) as (
            service,
            driver,
            _,
        ):
            async with asyncio.timeout(2.5 * DURATION_S / SPEED + 60):
                while sim.now_s < DURATION_S:  # noqa: ASYNC110 (the simulator's clock)
                    await asyncio.sleep(0.5)
            latencies = np.array(service.latencies_s)
            recentres = driver.recentres
    finally:
        ctx.term()
    records = RunStore(run_dir).frames()
    t_mid = np.array([0.5 * (r.t_start_s + r.t_end_s) for r in records])
    content = sim.physics.drift_at(t_mid) - sim.physics.scan_offset_at(t_mid)
    error = content - content[0]
    drift = sim.physics.drift_at(t_mid)
    return {
        "frames": float(len(records)),
        "rms_nm": float(np.sqrt(np.mean(np.sum(error**2, axis=1)))),
        "rms_after_10_frames_nm": float(np.sqrt(np.mean(np.sum(error[10:] ** 2, axis=1)))),
        "err_every_10": [round(float(np.hypot(*e)), 2) for e in error[::10]],  # type: ignore[dict-item]
        "max_nm": float(np.max(np.hypot(error[:, 0], error[:, 1]))),
        "drift_nm": float(np.max(np.hypot(*(drift - drift[0]).T))),
        "latency_p50_s": float(np.median(latencies)),
        "latency_p95_s": float(np.percentile(latencies, 95)),
        "recentres": float(recentres),
    }


@pytest.mark.timeout(600)
@pytest.mark.parametrize("actuator", ["offset", "velocity"])
async def test_two_hours_of_closed_loop_hold_the_image_while_the_sample_drifts(
    tmp_path: Path, actuator: str
) -> None:
    """Scan.FrameSet (offset) or Piezo.DriftCompSet (velocity): the loop is stable
    and holds the image content near its first position while the sample drifts
    by more than 50 nm.

    Issue 15 asks for 2 nm RMS; measured (benchmarks/RESULTS.md, 2026-11-26)
    1.90 to 1.92 nm through Scan.FrameSet and 1.55 nm through
    Piezo.DriftCompSet, against 120 to 132 nm of drift, every frame recorded.
    The guard leaves room for the run-to-run spread under CI load.
    """
    m = await _closed_loop(tmp_path / "run", actuator)
    print(f"closed loop via {actuator}: {m}")
    assert m["frames"] > 100
    assert m["drift_nm"] > 50.0
    assert m["rms_nm"] < 2.5
    assert m["rms_after_10_frames_nm"] < 2.0
    assert m["recentres"] == 0
