"""Add the missing effect to a running daemon and watch its rolling error fall.

The simulated instrument (served over loopback TCP) alternates up and down
frames with a scan-direction bias; the daemon's physics model starts without
the ``scan_direction`` term. After ``reload_model`` with a configuration that
adds it, the rolling one-step prediction error in the status stream falls.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
import zmq.asyncio
from service_sim import driver, running_service, scenario_data, service_config

from afmdrift.client import Subscriber, control
from afmdrift.config import parse_config
from afmdrift.drivers.sim import parse_scenario
from afmdrift.wire import FrameMsg, StatusMsg

ROLLING = 8


async def _rolling_after(sub: Subscriber, frames: int) -> float:
    """Rolling error from the first status after ``frames`` more frames arrived."""
    seen = 0
    while True:
        msg = await sub.recv()
        if isinstance(msg, FrameMsg):
            seen += 1
        elif isinstance(msg, StatusMsg) and seen >= frames and msg.rolling_error_nm is not None:
            return float(msg.rolling_error_nm)


@pytest.mark.slow
@pytest.mark.asyncio
async def test_reload_with_the_missing_effect_lowers_the_rolling_error(tmp_path: Path) -> None:
    from service_sim import sim_server

    data = scenario_data(seed=5, frame_period_s=32.0, drift_nm_per_sqrt_s=0.02, thermal=False)
    data["scan"]["directions"] = "alternate"
    data["physics"]["scan_direction"] = {"enabled": True, "bias_nm": [8.0, 6.0]}
    scenario = parse_scenario(data, source="reload-test")
    base = service_config(tmp_path / "run", rolling_window=ROLLING, reload_config_dir=str(tmp_path))
    model = {
        "predictor": "physics",
        "physics": {"terms": ["trend"], "residual": "ar1"},
    }
    cfg = parse_config(
        {
            "service": base.service.model_dump(),
            "registration": base.registration.model_dump(),
            "model": model,
        }
    )
    fixed = tmp_path / "fixed.toml"
    fixed.write_text(
        '[model]\npredictor = "physics"\n\n[model.physics]\n'
        'terms = ["trend", "scan_direction"]\nresidual = "ar1"\n',
        encoding="utf-8",
    )
    ctx = zmq.asyncio.Context()
    try:
        async with (
            sim_server(scenario, speed=100.0) as (_, url),
            running_service(cfg, driver(url), ctx) as service,
        ):
            sub = Subscriber(service.pub_endpoint, ctx=ctx)
            try:
                async with asyncio.timeout(240):
                    before = await _rolling_after(sub, 3 * ROLLING)
                    await control(
                        service.control_endpoint,
                        "reload_model",
                        config_path=str(fixed),
                        token_file=service.control_token_path,
                        timeout_s=60.0,
                        ctx=ctx,
                    )
                    assert service.pipeline.predictor.name == "physics"
                    after = await _rolling_after(sub, ROLLING + 2)
            finally:
                sub.close()
    finally:
        ctx.term()
    # The bias alternates with the frames, so a model without it misses by
    # about the bias every frame; with it, only noise and the random walk are left.
    assert before > 3.0
    assert after < 0.5 * before, (before, after)
