"""Issue 39: a controller the daemon checks instead of trusts.

The daemon's closed loop on the Nanonis simulator over loopback TCP, with
the velocity actuator (``Piezo.DriftCompSet``) and a small piezo range
(0.3 µm: the compensation's 10 % limit is 30 nm, so re-centring happens):

* a controller that resets the compensation's displacement on off/on and one
  that keeps it: the loop holds the image, with a bounded number of
  re-centres and frame moves;
* a compensation that applies half, or the negative, of the velocity asked:
  a re-centre's frame the books do not explain, or a loop that diverges,
  raises ``actuator_mismatch`` and the loop falls back to open loop.

Ground truth comes from the simulator (never over the wire): where image
content sits under the tip, ``p(t) − c(t) − q(t)``, every second of
instrument time from the end of the third frame.
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq.asyncio

from afmdrift.drivers.sim import SCENARIO_DIR, SimulatedAFM, load_scenario
from afmdrift.service import RunStore

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from service_sim import Residual, content_residual, nanonis_closed_loop

pytestmark = [pytest.mark.asyncio, pytest.mark.slow]

SPEED = 50.0
RANGE_NM = 300.0


async def _run(
    run_dir: Path, *, release: str, gain: float, duration_s: float, until_fault: bool = False
) -> dict[str, Any]:
    sc = load_scenario(SCENARIO_DIR / "default.toml")
    controller = {"release": release, "piezo_range_nm": (RANGE_NM, RANGE_NM, 2000.0)}
    sc = sc.model_copy(
        update={
            "controller": sc.controller.model_copy(update={**controller, "drift_comp_gain": gain})
        }
    )
    sim = SimulatedAFM(sc)
    ctx = zmq.asyncio.Context()
    try:
        async with nanonis_closed_loop(sim, run_dir, ctx, speed=SPEED) as (service, driver, server):
            loop = service.closed_loop
            async with asyncio.timeout(3.0 * duration_s / SPEED + 60):
                while sim.now_s < duration_s:
                    if until_fault and loop.fault is not None:
                        break
                    await asyncio.sleep(0.2)
            out: dict[str, Any] = {
                "fault": loop.fault,
                "checks": list(loop.checks),
                "flags": sorted(service.publishing.flags),
                "recentres": driver.recentres,
                "frame_sets": server.requests.get("Scan.FrameSet", 0),
                "t_end_s": sim.now_s,
            }
    finally:
        ctx.term()
    records = RunStore(run_dir).frames()
    out["records"] = records
    t_ref = 0.5 * (records[0].t_start_s + records[0].t_end_s)
    if len(records) > 3:
        t = np.arange(records[2].t_end_s, out["t_end_s"], 1.0)
        out["rms_nm"] = content_residual(sim.physics, t, t_ref_s=t_ref).rms_nm
        drift = sim.physics.drift_at(t) - sim.physics.drift_at([t_ref])
        out["drift_rms_nm"] = Residual.of(drift).rms_nm
    return out


@pytest.mark.timeout(600)
@pytest.mark.parametrize("release", ["reset", "keep"])
async def test_a_small_piezo_range_re_centres_within_the_bound_on_either_controller(
    tmp_path: Path, release: str
) -> None:
    """0.5 h of the default scenario on a 0.3 µm piezo. Measured (50×, this
    machine): 2.7 to 3.3 nm RMS against 54 nm of drift, 2 re-centres, either
    controller. At 50× an
    interval of the loop (0.1 s of wall time) is 5 s of instrument time: a
    re-centre's ramp-out shows for that long. The guard leaves room for
    the spread under CI load."""
    m = await _run(tmp_path / "run", release=release, gain=1.0, duration_s=1800.0)
    print({k: v for k, v in m.items() if k != "records"})
    assert m["fault"] is None
    assert "actuator_mismatch" not in m["flags"]
    assert m["drift_rms_nm"] > 30.0
    assert m["rms_nm"] < 5.0
    # the documented bound: one re-centre per minute of instrument time at
    # most, and none while the last one waits for its frame
    assert m["recentres"] <= 1800.0 / 60.0
    assert 1 <= m["recentres"] <= 6
    assert m["frame_sets"] == m["recentres"]
    assert all(v == "as booked" for _, _, v in m["checks"])


@pytest.mark.timeout(300)
async def test_a_compensation_of_the_wrong_sign_raises_the_alarm(tmp_path: Path) -> None:
    """The negative of the velocity asked: the loop diverges (or a re-centre's
    frame sits where the books do not put it), ``actuator_mismatch`` is
    raised and the loop falls back to open loop (no more moves). Measured:
    the fifth or sixth frame after the loop's first command; the issue asks
    for three (not met: the probe that would, closed_loop_probe_nm, is off
    by default, its frame also carrying the frame move's creep and play).
    Half the velocity asked is found only where a re-centre's frame shows it
    beyond the rolling errors, which the fault inflates (the fourth or the
    eighth frame in two runs): not tested here, it is too close to call."""
    m = await _run(tmp_path / "run", release="reset", gain=-1.0, duration_s=900.0, until_fault=True)
    print({k: v for k, v in m.items() if k != "records"})
    assert m["fault"] is not None
    assert "actuator_mismatch" in m["flags"]
    records = m["records"]
    first_curve = next(r.seq for r in records if r.fed_model and r.seq > 0)
    assert records[-1].seq - first_curve <= 7
    # re-centres within the bound (one per minute of instrument time); no storm
    assert m["frame_sets"] == m["recentres"] <= m["t_end_s"] / 60.0 + 1
