"""End to end: the effect the default model misses, added to the running daemon
from the shell, makes the one-step prediction error fall.

The simulated AFM (``afmdrift sim serve`` in its own process, on loopback
TCP) drifts with the relative humidity
it logs (channel ``humidity_pct``), as the hidden-effect study
``config/scenarios/hidden/humidity.toml`` does, on a faster clock. The daemon
runs the default physics model, which has no humidity term. After 40
frames, ``afmdrift control add-term humidity`` (a subprocess, as a user types
it) adds it; the one-step error RMS of the 20 frames after the change is at
most 0.7 times that of the 20 frames before, and every frame the instrument
made is in the run store exactly once. ``afmdrift diagnose`` on the run
then diagnoses the model with the term.
"""

from __future__ import annotations

import asyncio
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import zmq.asyncio
from service_sim import (
    SimProcess,
    driver,
    humid_scenario,
    run_afmdrift,
    running_service,
    service_config,
    write_scenario,
)

from afmdrift.config import parse_config
from afmdrift.dashboard import RunReader
from afmdrift.diagnostics import diagnose_path
from afmdrift.runs import RunStore

log = logging.getLogger(__name__)

BEFORE = 40
WINDOW = 20


def _rms(values: list[float]) -> float:
    v = np.asarray([x for x in values if math.isfinite(x)], dtype=np.float64)
    assert v.size >= WINDOW - 2, f"only {v.size} predicted frames in a window of {WINDOW}"
    return float(np.sqrt(np.mean(v**2)))


@pytest.mark.slow
@pytest.mark.asyncio
async def test_adding_the_missing_humidity_term_cuts_the_error(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    run = tmp_path / "run"
    base = service_config(run)
    cfg = parse_config(
        {
            "service": base.service.model_dump(),
            "registration": base.registration.model_dump(),
            "model": {"predictor": "physics"},  # the default terms: no humidity
        }
    )
    assert "humidity" not in cfg.model.physics.terms
    scenario_file = write_scenario(tmp_path / "humid.toml", humid_scenario(period_s=900.0))
    # 1.3 s a frame: a frame is replaced on the instrument only after the
    # daemon has had ample time to read it, even on a loaded machine
    sim = SimProcess(scenario_file, speed=15.0)
    url = sim.start()
    try:
        async with running_service(cfg, driver(url), ctx) as svc, asyncio.timeout(600):
            await svc.wait_for_frames(BEFORE)
            done = await asyncio.to_thread(
                run_afmdrift,
                "control", "add-term", "humidity",
                "--endpoint", svc.control_endpoint,
                "--token-file", str(svc.control_token_path),
                "--timeout-s", "60",
                cwd=tmp_path, timeout=120,
            )  # fmt: skip
            assert done.returncode == 0, done.stderr
            assert done.stdout.strip().endswith(", humidity")
            with RunReader(run) as reader:  # read-only, beside the daemon's writes
                (change,) = reader.model_changes()
            await svc.wait_for_frames(change.seq + 1 + WINDOW + 1)
            dropped = svc.frames_dropped
    finally:
        sim.kill()
    assert dropped == 0
    with RunStore(run) as store:
        records = store.frames()
        assert store.check_consistency() == []
    seqs = [r.seq for r in records]
    assert seqs == list(range(len(records)))  # none lost, none twice
    made = [r.instrument_frame for r in records]
    assert made == list(range(made[0], made[0] + len(made)))
    by_seq = {r.seq: r for r in records}
    before = _rms([by_seq[s].pred_error_nm for s in range(change.seq - WINDOW + 1, change.seq + 1)])
    after = _rms([by_seq[s].pred_error_nm for s in range(change.seq + 1, change.seq + 1 + WINDOW)])
    log.info(
        "humidity added after frame %d: one-step error RMS %.3f nm over the %d frames "
        "before, %.3f nm after (%.2f of it)", change.seq, before, WINDOW, after, after / before,
    )  # fmt: skip
    assert after <= 0.7 * before, (before, after)

    # diagnose reads the run with the terms it ended with: humidity is no longer missing
    diagnosis, data = diagnose_path(run, config=cfg)
    assert [(c.command, c.term) for c in data.model_changes] == [("add_term", "humidity")]
    assert diagnosis.model_effects == [*cfg.model.physics.terms, "humidity"]
    assert all(c.effect != "humidity" for c in diagnosis.candidates)
