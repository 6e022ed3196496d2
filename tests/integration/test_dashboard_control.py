"""The dashboard closes the loop: the live finding, "Add to model", and what it did.

Through the real transports: the simulator and the daemon (``afmdrift run``)
on loopback TCP, the dashboard's HTTP server, and, for the end-to-end case,
the page in headless Chromium.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import re
import sqlite3
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
import zmq.asyncio
from service_sim import REPO, driver, running_service, service_config, sim_server

from afmdrift.client import Subscriber, control
from afmdrift.config import parse_config
from afmdrift.dashboard import Dashboard
from afmdrift.dashboard._chromium import HeadlessChromium, find_chromium
from afmdrift.drivers.sim import load_scenario
from afmdrift.model import OffsetCurve
from afmdrift.wire import ModelMsg, OffsetMsg

pytestmark = [pytest.mark.asyncio]

HIDDEN = REPO / "config" / "scenarios" / "hidden"
SMALL_FRAMES = {"block_size": 32, "extended_size": 96}


async def _page(http: aiohttp.ClientSession, url: str) -> str:
    """Open the page as a browser does (``?token=``, then the cookie); its secret."""
    async with http.get(url) as r:
        assert r.status == 200
        html = await r.text()
    found = re.search(r'<meta name="afmdrift-csrf" content="([^"]+)">', html)
    assert found is not None
    return found.group(1)


async def _post(
    http: aiohttp.ClientSession, base: str, body: Any, headers: dict[str, str]
) -> tuple[int, dict[str, Any]]:
    async with http.post(base + "control/add_term", json=body, headers=headers) as r:
        return r.status, await r.json()


async def test_add_to_model_is_refused_without_token_secret_or_origin_and_for_a_bad_term(
    tmp_path: Path,
) -> None:
    """Every forged or bad "Add to model" request is refused with its reason and
    changes nothing: a dashboard without the control token, a wrong token, a
    missing or wrong page secret, a foreign or missing Origin, a term that does
    not parse. Then the real request from the page goes through."""
    ctx = zmq.asyncio.Context()
    scenario = load_scenario(HIDDEN / "control.toml")
    try:
        async with sim_server(scenario, speed=300.0) as (_, url):
            cfg = service_config(tmp_path / "run", model={}, registration=SMALL_FRAMES)
            async with running_service(cfg, driver(url), ctx) as service:
                token = service.control_token_path.read_text(encoding="utf-8")
                endpoint = service.control_endpoint
                before = await control(endpoint, "status", ctx=ctx)
                terms = list(cfg.model.physics.terms)
                assert before.status is not None
                assert before.status.terms == terms
                common: dict[str, Any] = {
                    "run_dir": tmp_path / "run",
                    "pub_endpoint": service.pub_endpoint,
                    "config": parse_config({}),
                    "ctx": ctx,
                }
                bare = Dashboard(**common, control_endpoint=endpoint)
                dash = Dashboard(
                    **common, token=token, control_endpoint=endpoint, control_token=token
                )
                # A browser keeps the page's cookie for 127.0.0.1 (aiohttp only when "unsafe").
                jar = aiohttp.CookieJar(unsafe=True)
                async with bare, dash, aiohttp.ClientSession(cookie_jar=jar) as http:
                    # A dashboard started without the daemon's token: the button is off.
                    base = bare.url
                    secret = await _page(http, base)
                    ok_headers = {"Origin": base.rstrip("/"), "X-Afmdrift-Csrf": secret}
                    status, body = await _post(http, base, {"term": "humidity"}, ok_headers)
                    assert status == 403
                    assert "without the daemon's control token" in body["error"]
                    summary = bare.state.summary(now_wall_s=0.0, silent_after_s=1.0)
                    assert summary["control"]["enabled"] is False

                    base = dash.url.split("?", 1)[0]
                    origin = base.rstrip("/")
                    async with aiohttp.ClientSession() as stranger:
                        # No token at all, and a wrong one: the page's own gate.
                        status, _ = await _post_text(stranger, base, {"Origin": origin})
                        assert status == 403
                        wrong = {"Origin": origin, "Authorization": "Bearer " + "x" * 43}
                        status, _ = await _post_text(stranger, base, wrong)
                        assert status == 403
                    secret = await _page(http, dash.url)
                    refusals = [
                        ({"Origin": origin}, 403, "secret is missing or wrong"),
                        ({"Origin": origin, "X-Afmdrift-Csrf": "forged"}, 403, "secret"),
                        (
                            {"Origin": "http://evil.example", "X-Afmdrift-Csrf": secret},
                            403,
                            "cross-site",
                        ),
                        ({"X-Afmdrift-Csrf": secret}, 403, "cross-site"),
                    ]
                    for headers, want, why in refusals:
                        status, body = await _post(http, base, {"term": "humidity"}, headers)
                        assert (status, body["ok"]) == (want, False), headers
                        assert why in body["error"], body
                    good = {"Origin": origin, "X-Afmdrift-Csrf": secret}
                    status, body = await _post(http, base, {"term": "humidity(((k"}, good)
                    assert status == 400
                    assert "humidity(((k" in body["error"]
                    status, body = await _post(http, base, {"terms": ["humidity"]}, good)
                    assert status == 400

                    # Nothing changed in the daemon.
                    after = await control(endpoint, "status", ctx=ctx)
                    assert after.status is not None
                    assert after.status.terms == terms
                    assert _model_changes(tmp_path / "run") == []

                    # The page's own request goes through (the token, the secret, same origin).
                    status, body = await _post(http, base, {"term": "humidity"}, good)
                    assert (status, body["ok"]) == (200, True), body
                    assert body["terms"] == [*terms, "humidity"]
                    assert [c[1] for c in _model_changes(tmp_path / "run")] == ["humidity"]
    finally:
        ctx.term()


async def _post_text(
    http: aiohttp.ClientSession, base: str, headers: dict[str, str]
) -> tuple[int, str]:
    async with http.post(
        base + "control/add_term", json={"term": "humidity"}, headers=headers
    ) as r:
        return r.status, await r.text()


def _model_changes(run_dir: Path) -> list[tuple[int, str | None, float, float]]:
    """``(seq, term, wall_s, handover_until_s)`` of the run's model changes, read
    beside the daemon."""
    with contextlib.closing(
        sqlite3.connect(f"file:{run_dir / 'run.sqlite'}?mode=ro", uri=True)
    ) as db:
        have = db.execute(
            "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'model_changes'"
        ).fetchone()
        if have is None:
            return []
        rows = db.execute(
            "SELECT seq, term, wall_s, handover_until_s FROM model_changes ORDER BY id"
        )
        return [
            (int(r[0]), r[1], float(r[2]), math.nan if r[3] is None else float(r[3])) for r in rows
        ]


def _frames(run_dir: Path) -> list[tuple[int, int, float | None, float | None]]:
    """``(seq, instrument_frame, pred_error_nm, pred_sigma_nm)`` of every stored frame."""
    with contextlib.closing(
        sqlite3.connect(f"file:{run_dir / 'run.sqlite'}?mode=ro", uri=True)
    ) as db:
        rows = db.execute(
            "SELECT seq, instrument_frame, x_nm - pred_x_nm, y_nm - pred_y_nm, pred_sigma_nm "
            "FROM frames ORDER BY seq"
        )
        return [
            (int(r[0]), int(r[1]), None if r[2] is None else math.hypot(r[2], r[3]), r[4])
            for r in rows
        ]


def _rms(values: list[float]) -> float:
    return math.sqrt(sum(v * v for v in values) / len(values))


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.skipif(find_chromium() is None, reason="chromium is not installed")
async def test_done_when_the_page_finds_humidity_adds_it_and_the_error_falls(
    tmp_path: Path,
) -> None:
    """Issue 41, done when: the simulator with humidity the default model lacks,
    the daemon on the default model, the dashboard in headless Chromium with the
    daemon's token. Within 60 frames the page names humidity; clicking "Add to
    model" adds it; the one-step error RMS over the 20 frames after the change
    is at most 0.7 of that over the 20 before; no frame is lost or processed
    twice; d(t) on the wire takes no step above max(prediction 1σ, 0.5 nm)."""
    ctx = zmq.asyncio.Context()
    run_dir = tmp_path / "run"
    scenario = load_scenario(HIDDEN / "humidity.toml")
    offsets: list[OffsetMsg] = []
    models: list[ModelMsg] = []
    try:
        # A frame every 4 wall seconds: the change's hand-over (its 1 s lead and
        # blend) ends before the next frame's curve (each frame's own update is
        # not what this test is about).
        async with sim_server(scenario, speed=75.0) as (_, url):
            cfg = service_config(
                run_dir, model={}, registration=SMALL_FRAMES, diagnose_every_frames=10
            )
            async with running_service(cfg, driver(url), ctx) as service:
                token = service.control_token_path.read_text(encoding="utf-8")
                sub = Subscriber(service.pub_endpoint, ctx=ctx, topics=["offset", "model"])

                async def follow() -> None:
                    while True:
                        msg = await sub.recv()
                        if isinstance(msg, OffsetMsg):
                            offsets.append(msg)
                        elif isinstance(msg, ModelMsg):
                            models.append(msg)

                follower = asyncio.create_task(follow())
                dash = Dashboard(
                    run_dir=run_dir,
                    pub_endpoint=service.pub_endpoint,
                    config=parse_config({}),
                    token=token,
                    control_endpoint=service.control_endpoint,
                    control_token=token,
                    store_poll_s=0.5,
                    ctx=ctx,
                )
                try:
                    async with dash, HeadlessChromium() as browser:
                        await browser.goto(dash.url)
                        await browser.wait_for(
                            "document.getElementById('live-finding').textContent"
                            ".includes('humidity')"
                            " && !document.getElementById('add-term').disabled",
                            timeout_s=400,
                        )
                        shown_at = service.frames_processed
                        assert shown_at <= 60, f"the finding came after {shown_at} frames"
                        term = await browser.evaluate(
                            "document.getElementById('add-term-term').textContent"
                        )
                        assert term == "humidity"
                        # Click just after a frame, as a user would at any moment
                        # between two: the hand-over then has the time to the next.
                        await service.wait_for_frames(service.frames_processed + 1)
                        await browser.evaluate("document.getElementById('add-term').click()")
                        await browser.wait_for(
                            "window.afmdriftDashboard.addTerm !== null", timeout_s=30
                        )
                        answer = await browser.evaluate("window.afmdriftDashboard.addTerm")
                        assert answer["status"] == 200, answer
                        (change_seq, added, change_wall_s, handover_until_s) = _model_changes(
                            run_dir
                        )[0]
                        assert added == "humidity"
                        await service.wait_for_frames(change_seq + 22)
                        # The page marks the change and measures before and after.
                        await browser.wait_for(
                            "window.afmdriftDashboard.changeMarks >= 1 && document"
                            ".getElementById('change-text').textContent.includes('frames after')",
                            timeout_s=30,
                        )
                        assert browser.errors == []
                        assert await browser.evaluate("window.afmdriftDashboard.lastError") is None
                finally:
                    follower.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await follower
                    sub.close()
        frames = _frames(run_dir)
        seqs = [f[0] for f in frames]
        assert seqs == list(range(len(frames)))
        inst = [f[1] for f in frames]
        assert inst == list(range(inst[0], inst[0] + len(inst))), "a frame lost or taken twice"
        by_seq = {f[0]: f for f in frames}
        before = [by_seq[s][2] for s in range(change_seq - 19, change_seq + 1)]
        after = [by_seq[s][2] for s in range(change_seq + 1, change_seq + 21)]
        assert None not in before
        assert None not in after
        ratio = _rms(after) / _rms(before)  # type: ignore[arg-type]
        assert ratio <= 0.7, (ratio, before, after)
        # d(t) on the wire across the change, from just before it to the end of its
        # hand-over (frames that come meanwhile included): no step above
        # max(prediction 1σ, 0.5 nm).
        sigma = by_seq[change_seq + 1][3] or 0.0
        limit = max(sigma, 0.5)
        near = [
            m
            for m in offsets
            if m.wall_s >= change_wall_s - 0.2 and m.t_s <= handover_until_s + 3.0
        ]
        curves_in = [round(m.wall_s - change_wall_s, 2) for m in models if m.frame > change_seq]
        # Consecutive samples at most two periods apart in wall time (100 Hz): the
        # interval the bound is kept for (a sample the loaded machine sent late
        # has more drift behind it).
        # The curve of the frame clicked after is taken up just before the change
        # (the click waits for it): that frame's own update, like every frame's,
        # is not the change's hand-over. The stream swaps curves on the event loop
        # and the model message's wall time is read right after the swap, so the
        # one pair of samples it falls between is that frame's own step.
        own_updates = [
            m.wall_s for m in models if m.frame <= change_seq and m.wall_s < change_wall_s
        ]
        pairs = [
            (a, b)
            for a, b in itertools.pairwise(near)
            if a.valid
            and b.valid
            and b.seq == a.seq + 1
            and b.wall_s - a.wall_s <= 0.02
            # and on the instrument's clock (docs/service.md: the bound is for
            # that interval; a step of the daemon's estimate of the 75× clock
            # puts a sample further on)
            and b.t_s - a.t_s <= 75.0 * 0.02
            and not any(a.wall_s < w < b.wall_s for w in own_updates)
        ]
        assert len(pairs) > 10
        # The bound is the documented one (docs/service.md): max(σ, 0.5 nm), or
        # the step the curve published before the change makes itself over
        # that interval where larger (at 75× a sample 0.013 s late is a second
        # of drift: 0.69 nm seen in CI, before the change).
        before_change = [m for m in models if m.wall_s < change_wall_s]
        old = OffsetCurve.from_dict(before_change[-1].curve)
        steps = [math.hypot(b.x_nm - a.x_nm, b.y_nm - a.y_nm) for a, b in pairs]
        own = [float(np.hypot(*(old.at([b.t_s]) - old.at([a.t_s]))[0])) for a, b in pairs]
        excess = [s - max(limit, 1.05 * o) for s, o in zip(steps, own, strict=True)]
        worst = max(range(len(steps)), key=excess.__getitem__)
        a, b = pairs[worst]
        limit = max(limit, 1.05 * own[worst])
        assert steps[worst] <= limit, (
            f"step {steps[worst]:.3f} nm > {limit:.3f} nm at {b.wall_s - change_wall_s:.3f} s "
            f"after the change, samples {b.wall_s - a.wall_s:.4f} s apart; hand-over to "
            f"t = {handover_until_s:.1f} s, sample at t = {b.t_s:.1f} s; frames published at "
            f"{curves_in[:6]}"
        )
    finally:
        ctx.term()
