"""``afmdrift run``: the drift daemon."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser(
        "run",
        help="Run the drift service (daemon) on an instrument.",
        description="Poll the instrument for frames, measure and predict drift, publish "
        "the offset d(t) over ZeroMQ and record everything in the run store. Stops "
        "cleanly on SIGINT/SIGTERM; restarted on the same run directory it resumes.",
    )
    p.add_argument(
        "--config", default=None, help="TOML configuration (default: config/default.toml)"
    )
    p.add_argument(
        "--instrument",
        default=None,
        help="instrument URL overriding [driver]: socket://127.0.0.1:N, a serial or pty "
        "path, or replay:SESSION_DIR",
    )
    p.add_argument("--run-dir", default=None, help="run directory overriding service.run_dir")
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    import asyncio

    from afmdrift.config import load_config
    from afmdrift.service import check_config, run_until_signalled

    config = load_config(args.config)
    if args.run_dir is not None:
        config = config.model_copy(
            update={"service": config.service.model_copy(update={"run_dir": args.run_dir})}
        )
    predictor, instrument = check_config(config, instrument_url=args.instrument)
    return asyncio.run(
        run_until_signalled(
            config=config, instrument=instrument, config_path=args.config, predictor=predictor
        )
    )
