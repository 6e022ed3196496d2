"""``afmdrift run``: the drift daemon."""

from __future__ import annotations

import argparse
import time
from typing import TYPE_CHECKING, Any

from afmdrift.cli._options import add_registration_options, registration_options

if TYPE_CHECKING:
    from afmdrift.service import DriftService


def register(sub: Any) -> None:
    p = sub.add_parser(
        "run",
        help="Run the drift service (daemon) on an instrument.",
        description="Poll the instrument for frames, measure and predict drift, publish "
        "the offset d(t) over ZeroMQ and record everything in the run store. Stops "
        "cleanly on SIGINT/SIGTERM; restarted on the same run directory it resumes. Prints "
        "what it serves and where once its sockets are bound (instrument, publish and "
        "control endpoints, run directory, predictor), and at the stop the frames processed "
        "and valid, the run time, the last drift position with its σ and the run directory.",
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
    add_registration_options(p)
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    import asyncio

    from afmdrift.config import load_config
    from afmdrift.service import check_config, run_until_signalled

    config = registration_options(args, load_config(args.config))
    if args.run_dir is not None:
        config = config.model_copy(
            update={"service": config.service.model_copy(update={"run_dir": args.run_dir})}
        )
    predictor, instrument = check_config(config, instrument_url=args.instrument)
    url = args.instrument or config.driver.transport
    started = time.time()
    return asyncio.run(
        run_until_signalled(
            config=config,
            instrument=instrument,
            config_path=args.config,
            predictor=predictor,
            on_ready=lambda service: print(_start_text(service, url), flush=True),
            on_stop=lambda service: print(_stop_text(service, started), flush=True),
        )
    )


def _start_text(service: DriftService, instrument_url: str) -> str:
    """What the daemon serves and where (its sockets bound, its store open)."""
    model = service.config.model
    terms = ""
    if model.predictor.startswith("physics"):
        terms = f" (terms: {', '.join(model.physics.terms)})"
    return "\n".join(
        [
            f"afmdrift run: drift service on instrument {instrument_url}",
            f"  publishing offset, model, frame and status on {service.pub_endpoint}",
            f"  control on {service.control_endpoint}",
            f"  run directory {service.svc.run_dir}",
            f"  predictor {model.predictor}{terms}, closed loop "
            f"{'on' if service.svc.closed_loop else 'off'}",
            "  SIGINT (Ctrl-C) or SIGTERM stops it",
        ]
    )


def _stop_text(service: DriftService, started: float) -> str:
    """One paragraph on what this run did: its frames (from the run store), its
    time, the last drift position it measured, where the run is."""
    from afmdrift.runs import RunStore

    with RunStore(service.svc.run_dir) as store:
        records = [r for r in store.frames() if r.wall_s >= started]
    valid = [r for r in records if r.valid]
    text = (
        f"afmdrift run: stopped after {time.time() - started:.1f} s; "
        f"{len(records)} frames processed, {len(valid)} valid"
    )
    if valid:
        last = valid[-1]
        text += (
            f"; last position x {last.x_nm:.2f} nm, y {last.y_nm:.2f} nm "
            f"(σ {last.sigma_nm:.2f} nm, frame {last.seq})"
        )
    return f"{text}; the run is in {service.svc.run_dir}"
