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
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import zmq.asyncio
from service_sim import (
    closed_port,
    driver,
    humid_scenario,
    running_service,
    service_config,
    sim_server,
)

from afmdrift.client import ControlRefusedError, Subscriber, control
from afmdrift.config import AfmdriftConfig, PhysicsConfig, parse_config
from afmdrift.dashboard import RunReader
from afmdrift.drivers.sim import parse_scenario
from afmdrift.pipeline import MIN_HANDOVER_STEP_NM
from afmdrift.runs import ModelChange
from afmdrift.service import DriftService
from afmdrift.wire import ModelMsg, OffsetMsg

log = logging.getLogger(__name__)

TERMS = ["trend", "warmup"]
#: The simulator's speed in the continuity test (instrument s per wall s).
SPEED = 10.0


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


def _largest_step_nm(offsets: list[OffsetMsg], interval_s: float) -> float:
    """The largest change between consecutive valid samples of the stream
    (consecutive sequence numbers) at most ``interval_s`` apart on the
    instrument's clock, the interval the hand-over keeps the bound for. (A
    sample further on follows a late tick, or a step of the daemon's estimate
    of an accelerated instrument's clock: d(t) jumps there by its slope.)"""
    steps = [
        math.hypot(b.x_nm - a.x_nm, b.y_nm - a.y_nm)
        for a, b in itertools.pairwise(offsets)
        if b.seq == a.seq + 1 and a.valid and b.valid and 0 < b.t_s - a.t_s <= interval_s
    ]
    assert len(steps) > 10, "too few consecutive offset samples around the change"
    return max(steps)


@pytest.mark.slow
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
    async with sim_server(scenario, speed=SPEED) as (_, url):
        svc = DriftService(config=cfg, instrument=driver(url), ctx=ctx, config_path=config_file)
        task = asyncio.create_task(svc.run())
        try:
            async with asyncio.timeout(240):
                await svc.ready.wait()
                await svc.wait_for_frames(12)
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
                # two offset periods (100 Hz) at the simulator's speed
                largest = _largest_step_nm(offsets, SPEED * 2.0 / 100.0)
                log.info(
                    "add_term: the new model predicts %.2f nm from the published d(t); "
                    "largest step %.3f nm (bound %.3f nm), handed over in %.1f s",
                    gap, largest, bound, change.handover_until_s - change.t_s,
                )  # fmt: skip
                assert largest <= bound
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        assert change.command == "add_term"
        assert change.term == "humidity"
        assert 11 <= change.seq < svc.frames_processed
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


@pytest.mark.asyncio
async def test_a_term_added_before_any_frame_outlives_a_restart(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    """No instrument, no frame: the change is still stored (no instrument time,
    nothing to hand over) and a daemon restarted on the run directory takes
    it up; a later reload_model takes the terms of its file again."""
    run = tmp_path / "run"
    cfg = physics_config(run, TERMS, reload_config_dir=str(tmp_path))
    url = f"socket://127.0.0.1:{closed_port()}"
    async with running_service(cfg, driver(url), ctx) as svc:
        reply = await control(
            svc.control_endpoint, "add_term", term="humidity",
            token_file=svc.control_token_path, ctx=ctx,
        )  # fmt: skip
        assert reply.status is not None
        assert reply.status.terms == [*TERMS, "humidity"]
    with RunReader(run) as reader:
        (change,) = reader.model_changes()
    assert change.seq == -1
    assert math.isnan(change.t_s)
    assert math.isnan(change.handover_until_s)
    async with running_service(cfg, driver(url), ctx) as again:
        assert await _status_terms(again, ctx) == [*TERMS, "humidity"]
        assert again.pipeline.predictor.config.terms == [*TERMS, "humidity"]  # type: ignore[attr-defined]
        file = tmp_path / "model.toml"
        file.write_text('[model]\npredictor = "physics"\n', encoding="utf-8")
        reply = await control(
            again.control_endpoint, "reload_model", config_path=str(file),
            token_file=again.control_token_path, ctx=ctx,
        )  # fmt: skip
        assert reply.status is not None
        assert reply.status.terms == list(PhysicsConfig().terms)
    assert stored_changes(run) == [
        ("add_term", (*TERMS, "humidity")),
        ("reload_model", tuple(PhysicsConfig().terms)),
    ]
    async with running_service(cfg, driver(url), ctx) as third:
        # the run's last reload_model took a file's terms; the daemon's own
        # configuration is read again, and no term change after it is replayed
        assert await _status_terms(third, ctx) == TERMS
