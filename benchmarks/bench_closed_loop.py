"""Closed-loop benchmark (issue 39): how well the daemon holds the tip on the spot.

For each physics (a scenario: by default the simulator's ``default`` and the
second physics ``heat-network-2h``) and each protocol, the daemon runs against
the simulator over loopback TCP for ``--duration-s`` of instrument time at
``--speed``, closing the loop:

* ``nanonis``: ``nanonis://``, ``closed_loop_actuator = "velocity"``
  (``Piezo.DriftCompSet``);
* ``line``: the NanoScope-style line protocol, ``closed_loop_actuator =
  "offset"`` (the only actuator that driver has).

Ground truth comes from the simulator, never from the wire: where image
content sits under the tip, ``c(t) = p(t) − o(t)`` (drift minus the scan
window's offset, compensation ramp included), sampled every ``--sample-s`` of
instrument time from the end of the third frame ``t_3`` to the end of the run,
relative to ``c(t_3)``. Beside it, from the same scenario and seed left
alone (a twin simulator with no loop, so without the creep and play that the
loop's own offset moves cause in the first physics), on the same interval:

* no compensation: ``p(t) − p(t_3)``;
* a constant velocity set once after the first two frames, taken from the
  truth: ``v = (p(t_m2) − p(t_m1)) / (t_m2 − t_m1)`` at the frames'
  mid-times, residual ``p(t) − p(t_3) − v (t − t_3)``.

Columns: RMS and peak of ``|residual|`` (nm), the ratio of the daemon's RMS to
the constant velocity's; the daemon's residual on the same interval relative
to where content sat at the first frame's mid-time instead (the daemon holds
content where its first frame, its reference, saw it, so an offset left at
``t_3`` by the loop's first corrections counts in the first measure and not in
this one); the driver's re-centres of the drift compensation
(Nanonis), the commanded offset moves the instrument logged
(``len(sim.physics.moves)``), and the frames the daemon committed.

The daemon runs with the project's default registration and model (no terms
chosen for a scenario; ``--terms`` replaces the model's terms) and the service
loops of the closed-loop soak test.
Runs are sequential (one daemon at a time).

Usage::

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_closed_loop.py \\
        [--duration-s 7200] [--speed 50] [--seed N] \\
        [--physics default heat-network-2h] [--protocols nanonis line] [--terms ...]
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import numpy.typing as npt
import zmq.asyncio

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))

from service_sim import (  # noqa: E402
    Residual,
    closed_loop_config,
    content_residual,
    driver,
    nanonis_closed_loop,
    running_service,
)

from afmdrift.drivers.sim import SimPhysics, SimulatedAFM  # noqa: E402
from afmdrift.drivers.sim._server import SimulatorServer  # noqa: E402
from afmdrift.service import RunStore  # noqa: E402

FloatArray = npt.NDArray[np.float64]

ACTUATOR = {"nanonis": "velocity", "line": "offset"}


def sample_times(frame_period_s: float, duration_s: float, step_s: float) -> FloatArray:
    """From the end of the third frame to ``duration_s``, every ``step_s``."""
    return np.arange(3.0 * frame_period_s, duration_s + 1e-9, step_s)


def baselines(
    physics: SimPhysics, frame_period_s: float, t: FloatArray
) -> tuple[Residual, Residual]:
    """No compensation and the constant velocity of the first two frames, on ``t``.

    ``t[0]`` is the end of the third frame; frames start every ``frame_period_s``
    from power-on.
    """
    p = physics.drift_at(t)
    p3 = p[0]
    t_m1, t_m2 = 0.5 * frame_period_s, 1.5 * frame_period_s
    v = (physics.drift_at(t_m2) - physics.drift_at(t_m1)) / (t_m2 - t_m1)
    none = Residual.of(p - p3)
    constant = Residual.of(p - p3 - (t - t[0])[:, None] * v[None, :])
    return none, constant


@dataclasses.dataclass(frozen=True)
class CaseResult:
    physics: str
    protocol: str
    afmdrift: Residual
    held: Residual
    none: Residual
    constant: Residual
    recentres: int | None
    moves: int
    frames: int
    wall_s: float


async def _hold(sim: SimulatedAFM, duration_s: float, speed: float) -> None:
    async with asyncio.timeout(2.5 * duration_s / speed + 60):
        while sim.now_s < duration_s:  # noqa: ASYNC110 (the simulator's clock)
            await asyncio.sleep(0.5)


async def run_case(
    scenario: str,
    protocol: str,
    *,
    duration_s: float,
    speed: float,
    seed: int | None,
    run_dir: Path,
    terms: list[str] | None = None,
) -> tuple[SimulatedAFM, int | None, int]:
    """Run the daemon against the simulator; the simulator, re-centres and frames."""
    sim = SimulatedAFM.from_scenario(scenario, seed=seed)
    ctx = zmq.asyncio.Context()
    recentres: int | None = None
    try:
        if protocol == "nanonis":
            async with nanonis_closed_loop(
                sim, run_dir, ctx, speed=speed, actuator=ACTUATOR[protocol], terms=terms
            ) as (_, nanonis, _):
                await _hold(sim, duration_s, speed)
            recentres = nanonis.recentres
        else:
            cfg = closed_loop_config(run_dir, ACTUATOR[protocol], terms=terms)
            server = SimulatorServer(sim, speed=speed)
            try:
                port = await server.start_tcp(0, host="127.0.0.1")
                async with running_service(cfg, driver(f"socket://127.0.0.1:{port}"), ctx):
                    await _hold(sim, duration_s, speed)
            finally:
                await server.stop()
    finally:
        ctx.term()
    return sim, recentres, len(RunStore(run_dir).frames())


def measure(
    scenario: str,
    protocol: str,
    *,
    duration_s: float,
    speed: float,
    seed: int | None,
    step_s: float,
    terms: list[str] | None = None,
) -> CaseResult:
    with tempfile.TemporaryDirectory(prefix="bench-closed-loop-") as tmp:
        t0 = time.perf_counter()
        sim, recentres, frames = asyncio.run(
            run_case(
                scenario,
                protocol,
                duration_s=duration_s,
                speed=speed,
                seed=seed,
                run_dir=Path(tmp) / "run",
                terms=terms,
            )
        )
        wall = time.perf_counter() - t0
    t = sample_times(sim.frame_period_s, duration_s, step_s)
    # The baselines from a twin left alone: in the first physics the loop's own
    # offset moves add creep and play to p(t), which no compensation would not have.
    twin = SimulatedAFM.from_scenario(scenario, seed=seed)
    twin.advance_to(duration_s)
    none, constant = baselines(twin.physics, twin.frame_period_s, t)
    return CaseResult(
        physics=scenario,
        protocol=protocol,
        afmdrift=content_residual(sim.physics, t, t_ref_s=float(t[0])),
        held=content_residual(sim.physics, t, t_ref_s=0.5 * sim.frame_period_s),
        none=none,
        constant=constant,
        recentres=recentres,
        moves=len(sim.physics.moves),
        frames=frames,
        wall_s=wall,
    )


def table(results: list[CaseResult]) -> str:
    head = (
        "| physics | protocol (actuator) | no compensation RMS / peak | constant velocity "
        "RMS / peak | afmdrift RMS / peak | afmdrift / constant RMS | afmdrift from the first "
        "frame RMS / peak | re-centres | offset moves | frames | wall |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|"
    )
    rows = [head]
    for r in results:
        rc = "–" if r.recentres is None else str(r.recentres)
        rows.append(
            f"| {r.physics} | {r.protocol} ({ACTUATOR[r.protocol]}) "
            f"| {r.none.rms_nm:.1f} / {r.none.peak_nm:.1f} nm "
            f"| {r.constant.rms_nm:.1f} / {r.constant.peak_nm:.1f} nm "
            f"| {r.afmdrift.rms_nm:.2f} / {r.afmdrift.peak_nm:.1f} nm "
            f"| {r.afmdrift.rms_nm / r.constant.rms_nm:.3f} "
            f"| {r.held.rms_nm:.2f} / {r.held.peak_nm:.1f} nm | {rc} | {r.moves} | {r.frames} "
            f"| {r.wall_s:.0f} s |"
        )
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration-s", type=float, default=7200.0, help="instrument time per run")
    ap.add_argument("--speed", type=float, default=50.0, help="instrument clock / wall clock")
    ap.add_argument("--seed", type=int, default=None, help="default: each scenario's own")
    ap.add_argument("--physics", nargs="+", default=["default", "heat-network-2h"])
    ap.add_argument("--protocols", nargs="+", choices=sorted(ACTUATOR), default=["nanonis", "line"])
    ap.add_argument("--sample-s", type=float, default=1.0, help="truth sampling step")
    ap.add_argument(
        "--terms", nargs="+", default=None, help="the model's terms (default: the project's)"
    )
    args = ap.parse_args(argv)
    results = []
    for scenario in args.physics:
        for protocol in args.protocols:
            r = measure(
                scenario,
                protocol,
                duration_s=args.duration_s,
                speed=args.speed,
                seed=args.seed,
                step_s=args.sample_s,
                terms=args.terms,
            )
            print(f"{scenario} / {protocol}: {r}", file=sys.stderr, flush=True)
            results.append(r)
    print(table(results))


if __name__ == "__main__":
    main()
