"""Adding an effect term to the running model (control ``add_term``, ``remove_term``).

Through the real transports: the simulated AFM served on loopback TCP, the
daemon's control socket and its ZeroMQ offset stream, the run store read
back read-only. A refused change leaves the status terms and the store as
they were; an accepted one is stored, shown in the status, kept by a daemon
restarted on the same run directory, and d(t) hands over to it without a
step larger than max(the prediction's 1σ, 0.5 nm) between offset samples.
"""

from __future__ import annotations

import asyncio
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import zmq.asyncio
from service_sim import (
    closed_port,
    driver,
    running_service,
    scenario_data,
    service_config,
    sim_server,
)

from afmdrift.client import ControlRefusedError, Subscriber, control
from afmdrift.config import AfmdriftConfig, parse_config
from afmdrift.dashboard import RunReader
from afmdrift.drivers.sim import parse_scenario
from afmdrift.pipeline import MIN_HANDOVER_STEP_NM
from afmdrift.runs import ModelChange
from afmdrift.service import DriftService
from afmdrift.wire import ModelMsg, OffsetMsg

TERMS = ["trend", "warmup"]


def physics_config(
    run_dir: Path, terms: list[str], *, blend_fraction: float = 0.1, **service: object
) -> AfmdriftConfig:
    base = service_config(run_dir, **service)
    return parse_config(
        {
            "service": base.service.model_dump(),
            "registration": base.registration.model_dump(),
            "model": {
                "predictor": "physics",
                "physics": {"terms": terms, "residual": "ar1"},
                "blend_fraction": blend_fraction,
            },
        }
    )


def stored_changes(run_dir: Path) -> list[tuple[str, tuple[str, ...] | None]]:
    """The model changes in the run store, read as the dashboard reads it."""
    with RunReader(run_dir) as reader:
        return [(c.command, c.terms_after) for c in reader.model_changes()]


async def _status_terms(svc: DriftService, ctx: zmq.asyncio.Context) -> list[str] | None:
    reply = await control(svc.control_endpoint, "status", ctx=ctx)
    assert reply.status is not None
    return reply.status.terms


@pytest.mark.asyncio
async def test_refused_term_changes_change_nothing(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    """No token, a wrong token, a term that does not parse, an unknown term, a
    term already there, removing an absent term, no term at all: each is
    refused with a reply naming why; the terms and the store stay as they were."""
    run = tmp_path / "run"
    cfg = physics_config(run, TERMS)
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        ep, tok = svc.control_endpoint, svc.control_token_path
        assert await _status_terms(svc, ctx) == TERMS
        cases: list[tuple[str, str | None, dict[str, object], str]] = [
            ("add_term", "humidity", {}, "no token"),
            ("add_term", "humidity", {"token": "not-the-token"}, "wrong token"),
            ("remove_term", "trend", {}, "no token"),
            ("add_term", "jump:19200", {"token_file": tok}, "expected 'jump:t_s="),
            ("add_term", "no_such_effect", {"token_file": tok}, "unknown term"),
            ("add_term", "trend", {"token_file": tok}, "already a term"),
            ("remove_term", "humidity", {"token_file": tok}, "not a term"),
            ("add_term", None, {"token_file": tok}, "needs 'term'"),
            ("add_term", "   ", {"token_file": tok}, "needs a term"),
        ]
        for cmd, term, auth, why in cases:
            with pytest.raises(ControlRefusedError, match=why) as refused:
                await control(ep, cmd, term=term, ctx=ctx, **auth)  # type: ignore[arg-type]
            assert refused.value.reply.ok is False
            assert await _status_terms(svc, ctx) == TERMS, (cmd, term)
            assert svc.controller.config.model.physics.terms == TERMS
    assert stored_changes(run) == []


@pytest.mark.asyncio
async def test_add_term_needs_the_physics_model(tmp_path: Path, ctx: zmq.asyncio.Context) -> None:
    """A predictor without terms refuses add_term, naming the predictor."""
    run = tmp_path / "run"
    cfg = service_config(run)  # constant_velocity
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        assert await _status_terms(svc, ctx) is None
        no_terms = "'constant_velocity', which has no effect terms"
        with pytest.raises(ControlRefusedError, match=no_terms):
            await control(
                svc.control_endpoint, "add_term", term="humidity",
                token_file=svc.control_token_path, ctx=ctx,
            )  # fmt: skip
        assert svc.pipeline.predictor.name == "constant_velocity"
    assert stored_changes(run) == []


def humid_scenario(*, period_s: float = 600.0, beta_nm_per_pct: float = 6.0) -> dict[str, object]:
    """Drift that follows the logged relative humidity (a cycle of 5 %RH).

    A model without the ``humidity`` term follows it late, through its
    residual; adding the term moves the prediction by several nm at once
    (what d(t) must not jump by)."""
    data = scenario_data(
        seed=5, frame_period_s=20.0, line_rate_hz=8.0, drift_nm_per_sqrt_s=0.02, thermal=False
    )
    data["physics"]["humidity"] = {
        "enabled": True,
        "mean_pct": 45.0,
        "amplitude_pct": 5.0,
        "period_s": period_s,
        "fluctuation_pct": 0.2,
        "beta_nm_per_pct": [beta_nm_per_pct, -0.7 * beta_nm_per_pct],
    }
    return data


async def _offsets_through_change(
    svc: DriftService, ctx: zmq.asyncio.Context, sub: Subscriber, run: Path, term: str
) -> tuple[list[OffsetMsg], ModelChange]:
    """Offset samples from a few before ``add_term`` until the next frame's
    model replaces the change's curve; and the change as the store has it."""
    offsets: list[OffsetMsg] = []
    tok = svc.control_token_path
    request = control(
        svc.control_endpoint, "add_term", term=term, token_file=tok, timeout_s=60.0, ctx=ctx
    )
    task = asyncio.create_task(request)
    change: ModelChange | None = None
    newest_model = -1
    try:
        while change is None or newest_model <= change.seq:
            msg = await sub.recv()
            if isinstance(msg, OffsetMsg):
                offsets.append(msg)
            elif isinstance(msg, ModelMsg):
                newest_model = max(newest_model, msg.frame)
            if change is None and task.done():
                with RunReader(run) as reader:
                    (change,) = reader.model_changes()
    finally:
        reply = await task
    assert reply.ok
    return offsets, change


def _largest_step_nm(offsets: list[OffsetMsg], rate_hz: float) -> float:
    """The largest change between consecutive valid samples of the stream
    (consecutive sequence numbers, at most two periods of ``rate_hz`` apart
    in wall time: the interval the bound is kept for)."""
    steps = [
        math.hypot(b.x_nm - a.x_nm, b.y_nm - a.y_nm)
        for a, b in itertools.pairwise(offsets)
        if b.seq == a.seq + 1 and a.valid and b.valid and b.wall_s - a.wall_s <= 2.0 / rate_hz
    ]
    assert len(steps) > 10, "too few consecutive offset samples around the change"
    return max(steps)


@pytest.mark.asyncio
async def test_add_term_is_stored_shown_continuous_and_kept_on_restart(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    """add_term with a valid term: a model_change row with the terms before and
    after, the status shows the term, the offset stream hands over without a
    step above max(σ, 0.5 nm), and a daemon restarted on the run directory
    (its configuration file untouched) keeps the term."""
    run = tmp_path / "run"
    # Each frame's curve hands over within a whole frame period: the stream's
    # own steps stay well under the bound, so a step from the change would show.
    cfg = physics_config(run, ["trend"], blend_fraction=1.0, offset_rate_hz=100.0)
    config_file = tmp_path / "afmdrift.toml"
    config_file.write_text('[model]\npredictor = "physics"\n', encoding="utf-8")
    config_bytes = config_file.read_bytes()
    scenario = parse_scenario(humid_scenario(), source="add-term-test")
    async with sim_server(scenario, speed=10.0) as (_, url):
        svc = DriftService(config=cfg, instrument=driver(url), ctx=ctx, config_path=config_file)
        task = asyncio.create_task(svc.run())
        try:
            async with asyncio.timeout(240):
                await svc.ready.wait()
                await svc.wait_for_frames(6)
                sub = Subscriber(svc.pub_endpoint, topics=("offset", "model"), ctx=ctx)
                try:
                    await sub.recv()  # the subscription is up
                    before = svc.pipeline.curve
                    assert before is not None
                    offsets, change = await _offsets_through_change(svc, ctx, sub, run, "humidity")
                finally:
                    sub.close()
                assert await _status_terms(svc, ctx) == ["trend", "humidity"]
                # the refitted model predicts several nm away from the old curve:
                # without the hand-over, d(t) would step by that much
                new = svc.pipeline.predictor.predict_drift([change.t_s], svc.pipeline.history)
                gap = float(np.hypot(*(new.mean_nm[0] - before.at([change.t_s])[0])))
                bound = change.step_bound_nm
                assert bound >= MIN_HANDOVER_STEP_NM
                assert change.handover_until_s > change.t_s
                assert gap > 3 * bound, (gap, bound)
                assert _largest_step_nm(offsets, 100.0) <= bound
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        assert change.command == "add_term"
        assert change.term == "humidity"
        assert 5 <= change.seq < svc.frames_processed
        assert change.terms_before == ("trend",)
        assert change.terms_after == ("trend", "humidity")
        assert stored_changes(run) == [("add_term", ("trend", "humidity"))]

        # the same run directory, the same configuration: the term stays
        again = DriftService(config=cfg, instrument=driver(url), ctx=ctx, config_path=config_file)
        task = asyncio.create_task(again.run())
        try:
            async with asyncio.timeout(120):
                await again.ready.wait()
                assert await _status_terms(again, ctx) == ["trend", "humidity"]
                assert again.pipeline.predictor.config.terms == ["trend", "humidity"]  # type: ignore[attr-defined]
                frames = again.frames_processed
                await again.wait_for_frames(frames + 2)
                reply = await control(
                    again.control_endpoint, "remove_term", term="humidity",
                    token_file=again.control_token_path, timeout_s=60.0, ctx=ctx,
                )  # fmt: skip
                assert reply.status is not None
                assert reply.status.terms == ["trend"]
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
    assert config_file.read_bytes() == config_bytes
    assert stored_changes(run) == [
        ("add_term", ("trend", "humidity")),
        ("remove_term", ("trend",)),
    ]
