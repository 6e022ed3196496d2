"""End to end over a pseudo-terminal: simulator ⇄ driver ⇄ daemon ⇄ subscriber.

Ground truth comes from the simulator's own drift model (never sent over the
wire): the measured drift position of each frame is compared with the mean of
the true drift over that frame's scan lines, relative to the reference frame.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import sqlite3
import time
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import zmq.asyncio
from service_sim import driver, running_service, service_config, sim_server, small_scenario

from afmdrift.client import Subscriber
from afmdrift.drivers import Frame, ScanDirection
from afmdrift.model import truth_frame_mean
from afmdrift.service import RunStore
from afmdrift.wire import FrameMsg, ModelMsg, OffsetMsg, encode

pytestmark = [pytest.mark.asyncio, pytest.mark.slow]


def _schema_validator(name: str) -> jsonschema.Draft202012Validator:
    path = Path(__file__).resolve().parents[2] / "docs" / "schemas" / f"{name}.schema.json"
    return jsonschema.Draft202012Validator(json.loads(path.read_text(encoding="utf-8")))


def _frame_like(t_start_s: float, t_end_s: float, rows: int) -> Frame:
    return Frame(
        index=0,
        heights_nm=np.zeros((rows, 1)),
        pixel_size_nm=(1.0, 1.0),
        t_start_s=t_start_s,
        t_end_s=t_end_s,
        direction=ScanDirection.UP,
    )


async def test_pty_end_to_end_tracks_truth_and_publishes_every_topic(tmp_path: Path) -> None:
    ctx = zmq.asyncio.Context()
    scenario = small_scenario(drift_nm_per_sqrt_s=0.1)
    frames: list[FrameMsg] = []
    models: list[ModelMsg] = []
    offsets: list[OffsetMsg] = []
    checked_offset_at = 0
    try:
        async with sim_server(scenario, speed=100.0, transport="pty") as (server, url):
            assert url.startswith("/dev/")
            cfg = service_config(tmp_path / "run", offset_rate_hz=100.0)
            async with running_service(cfg, driver(url), ctx) as service:
                sub = Subscriber(service.pub_endpoint, ctx=ctx)
                try:
                    async with asyncio.timeout(60):
                        while len(frames) < 14:
                            msg = await sub.recv()
                            if isinstance(msg, FrameMsg):
                                frames.append(msg)
                            elif isinstance(msg, ModelMsg):
                                models.append(msg)
                            elif isinstance(msg, OffsetMsg):
                                offsets.append(msg)
                                model = sub.model
                                # The subscriber's own evaluation of the latest model
                                # agrees with the published stream (same curve).
                                if (
                                    msg.valid
                                    and not msg.clamped
                                    and model is not None
                                    and model.wall_s < msg.wall_s - 0.05
                                ):
                                    x, y = sub.offset_at(msg.t_s)
                                    assert x == pytest.approx(msg.x_nm, abs=1e-6)
                                    assert y == pytest.approx(msg.y_nm, abs=1e-6)
                                    checked_offset_at += 1
                    assert not sub.is_stale()
                finally:
                    sub.close()
                stored = RunStore(tmp_path / "run").frames()
            truth = server.sim
    finally:
        ctx.term()

    assert checked_offset_at > 50
    # the frame and model messages sent satisfy the published JSON Schemas
    for name, msgs in (("frame", frames), ("model", models), ("offset", offsets[-5:])):
        validator = _schema_validator(name)
        for m in msgs:
            validator.validate(json.loads(encode(m)[1]))
    # every frame the daemon saw is in the store, in order, exactly once (a
    # busy machine may let the instrument replace a frame before it is read:
    # the daemon says so, and such misses stay rare)
    assert [r.seq for r in stored] == list(range(len(stored)))
    indices = [r.instrument_frame for r in stored]
    assert all(b > a for a, b in itertools.pairwise(indices))
    assert indices[-1] - indices[0] + 1 - len(indices) <= 0.15 * len(indices), indices
    assert len(stored) >= len(frames)
    # the reference frame, then measurements that follow the true drift
    assert stored[0].reason == "reference"
    ref_truth = truth_frame_mean(
        _frame_like(stored[0].t_start_s, stored[0].t_end_s, stored[0].rows),
        *_truth_table(truth, stored[0].t_start_s, stored[-1].t_end_s),
    )
    errors = []
    for r in stored[1:]:
        assert r.fed_model, r.reason
        true_p = (
            truth_frame_mean(
                _frame_like(r.t_start_s, r.t_end_s, r.rows),
                *_truth_table(truth, stored[0].t_start_s, stored[-1].t_end_s),
            )
            - ref_truth
        )
        errors.append(math.hypot(r.x_nm - true_p[0], r.y_nm - true_p[1]))
    assert max(errors) < 1.0, errors  # 4 nm pixels: sub-pixel agreement
    # one model message per fed frame, prediction errors scored from frame 2 on
    assert len(models) >= len(frames) - 1
    assert all(f.pred_error_nm is not None for f in frames if f.frame >= 2)
    # offset stream: no gap in what this subscriber received, rate near 100 Hz
    seqs = [o.seq for o in offsets]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    span = offsets[-1].wall_s - offsets[0].wall_s
    assert 60 < len(offsets) / span < 140
    # the service closed its store: a reader sees a WAL database with every frame
    with sqlite3.connect(tmp_path / "run" / "run.sqlite") as db:
        assert db.execute("SELECT COUNT(*) FROM frames").fetchone()[0] == len(stored)


def _truth_table(sim: object, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(t0, t1, int((t1 - t0) / 0.25) + 2)
    x, y = sim.truth_at(t)  # type: ignore[attr-defined]
    return t, np.stack([x, y], axis=1)


async def test_closed_loop_keeps_the_image_on_the_same_spot(tmp_path: Path) -> None:
    """With closed_loop the service moves the scan offset by the predicted drift:
    the image content stays put (small measured image positions) while the drift
    position p, which adds back the service's own offset moves, follows the truth."""
    ctx = zmq.asyncio.Context()
    scenario = small_scenario(drift_nm_per_sqrt_s=0.0, seed=3, warmup_nm=(300.0, -200.0))
    try:
        async with sim_server(scenario, speed=100.0, transport="tcp") as (server, url):
            cfg = service_config(
                tmp_path / "run",
                closed_loop=True,
                closed_loop_interval_s=0.05,
                closed_loop_min_step_nm=0.0,
            )
            async with running_service(cfg, driver(url), ctx) as service:
                async with asyncio.timeout(90):
                    await service.wait_for_frames(16)
                moves = [e for e in server.sim.events if e.kind.value == "offset_move"]
            stored = RunStore(tmp_path / "run").frames()
    finally:
        ctx.term()
    assert len(moves) > 5
    late = stored[-6:]
    p = np.array([[r.x_nm, r.y_nm] for r in late])
    m = np.array([[r.image_x_nm, r.image_y_nm] for r in late])
    o = np.array([[r.offset_x_nm, r.offset_y_nm] for r in late])
    np.testing.assert_allclose(p, m + o, atol=1e-9)
    # the sample drifted by tens of nm, the compensated image by about 1 nm
    assert np.abs(p).max() > 20.0
    assert np.abs(m).max() < 2.0


async def test_stream_goes_stale_without_frames_and_recovers(tmp_path: Path) -> None:
    """No frame for more than stale_factor expected intervals: status 'stale' and
    invalid offsets; scanning again clears it."""
    ctx = zmq.asyncio.Context()
    try:
        async with sim_server(small_scenario(), speed=100.0) as (server, url):
            cfg = service_config(tmp_path / "run")
            async with running_service(cfg, driver(url), ctx) as service:
                async with asyncio.timeout(30):
                    await service.wait_for_frames(3)
                server.sim.stop()  # the scanner stops; the clock goes on
                async with asyncio.timeout(10):
                    await service.wait_for_flag("stale")
                assert service.status_msg().state == "stale"
                # the next offset samples after the flag (however slow the machine)
                flagged = time.time()
                async with asyncio.timeout(10):
                    while (last := service.last_offset) is None or last.wall_s <= flagged:  # noqa: ASYNC110
                        await asyncio.sleep(0.01)
                assert not last.valid
                n = service.frames_processed
                server.sim.start()
                async with asyncio.timeout(30):
                    await service.wait_for_frames(n + 2)
                assert "stale" not in service.status_msg().flags
    finally:
        ctx.term()


async def test_daemon_on_a_replayed_session_matches_afmdrift_replay(tmp_path: Path) -> None:
    """The daemon over ``replay:SESSION`` and ``afmdrift replay`` run the same per-frame
    code: the same frames give the same drift positions."""
    from afmdrift.drivers.sim._record import record_session
    from afmdrift.runs import measure_session, series_from_records
    from afmdrift.service import open_instrument, replay_session
    from afmdrift.session import read_session

    session = record_session(
        small_scenario(warmup_nm=(80.0, -50.0)), tmp_path / "session", frames=8
    ).path
    cfg = service_config(tmp_path / "daemon-run")
    # replay_speed 0: one new frame each time the daemon polls, as fast as it can
    cfg = cfg.model_copy(update={"driver": cfg.driver.model_copy(update={"replay_speed": 0.0})})
    replay_session(session, tmp_path / "replay-run", config=cfg)
    ctx = zmq.asyncio.Context()
    try:
        instrument = open_instrument(cfg, url=f"replay:{session}")
        async with running_service(cfg, instrument, ctx) as service:
            async with asyncio.timeout(60):
                await service.wait_for_frames(8)
    finally:
        ctx.term()
    daemon = RunStore(tmp_path / "daemon-run").frames()
    replay = RunStore(tmp_path / "replay-run").frames()
    assert [r.instrument_frame for r in daemon] == [r.instrument_frame for r in replay]
    for a, b in zip(daemon, replay, strict=True):
        assert a.x_nm == pytest.approx(b.x_nm, abs=1e-9, nan_ok=True)
        assert a.y_nm == pytest.approx(b.y_nm, abs=1e-9, nan_ok=True)
        assert a.fed_model == b.fed_model
    # the same drift trajectory, written by both
    traj_daemon = np.loadtxt(tmp_path / "daemon-run" / "trajectory.csv", delimiter=",", skiprows=1)
    traj_replay = np.loadtxt(tmp_path / "replay-run" / "trajectory.csv", delimiter=",", skiprows=1)
    assert traj_daemon.shape[0] >= 7 * 2
    np.testing.assert_allclose(traj_daemon, traj_replay, atol=1e-9)
    # and `afmdrift evaluate` scores the observations the daemon fed its model
    series = measure_session(read_session(session), cfg)
    fed = series_from_records(daemon)
    np.testing.assert_allclose(series.t_s, fed.t_s, atol=1e-9)
    np.testing.assert_allclose(series.xy_nm, fed.xy_nm, atol=1e-9)
