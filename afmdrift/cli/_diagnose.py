"""``afmdrift diagnose RUN_DIR|SESSION``: model against measurement."""

from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
from typing import Any

from afmdrift.cli._options import (
    PRIOR_HELP,
    add_prior_option,
    add_registration_options,
    prior_option,
    registration_options,
)


def register(sub: Any) -> None:
    p = sub.add_parser(
        "diagnose",
        help="Compare the drift model with the measurements; find the missing effect.",
        description="Run SESSION through the drift service's pipeline (as `afmdrift replay` "
        "does) or read an existing RUN_DIR, then compare the physics model's one-step "
        "predictions with the measured drift, locate failure episodes, and test every "
        "library effect the model lacks and the response to every logged channel and event "
        "kind (added-variable fits with autocorrelation-robust errors, AICc, blocked "
        "cross-validation and an online re-run). Prints a plain-language finding with "
        "the configuration line to add; see docs/tutorial-diagnose.md.",
    )
    p.add_argument("path", metavar="RUN_DIR|SESSION", help="run directory or session directory")
    p.add_argument("--config", help="TOML configuration file (default: config/default.toml)")
    p.add_argument(
        "--effects",
        help="comma-separated model terms, e.g. trend,thermal_lag,creep,channel:pressure_hpa "
        "(library names or term specs, docs/model.md; default: [model.physics] terms of "
        "the configuration)",
    )
    p.add_argument(
        "--json", action="store_true", help="print the JSON object (docs/diagnostics.md)"
    )
    p.add_argument("--report", metavar="OUT.html", help="write a self-contained HTML report")
    p.add_argument(
        "--run-dir",
        help="for a SESSION: keep the replayed run here (empty or new directory; "
        "default: a temporary directory)",
    )
    p.add_argument(
        "--session",
        help="for a RUN_DIR: the session it came from (true drift, frames for the vector field)",
    )
    p.add_argument(
        "--burn-in",
        type=int,
        default=10,
        help="first fed frames left out of the error statistics (default 10)",
    )
    p.add_argument(
        "--workers",
        type=int,
        help="processes for the candidates' online re-runs, side by side "
        "(default: one per core this process may use; 1 runs them in this process)",
    )
    p.add_argument(
        "--look",
        type=int,
        help="this diagnosis is the K-th of a sequence over one growing run (the daemon's "
        "live diagnoses): its candidates are tested at alpha*6/(pi^2*K^2), so the whole "
        "sequence raises a false alarm with probability at most alpha "
        "(docs/diagnostics.md, Repeated diagnoses)",
        metavar="K",
    )
    p.add_argument(
        "--snapshot",
        action="store_true",
        help="for a RUN_DIR a daemon is writing: read a consistent copy of its store "
        "(SQLite online backup into a temporary directory) instead of the live file",
    )
    add_prior_option(
        p, help=PRIOR_HELP + " (a SESSION only: a run directory is read as it was measured)"
    )
    add_registration_options(p)
    p.set_defaults(handler=_diagnose)


def _diagnose(args: argparse.Namespace) -> int:
    from afmdrift.config import load_config
    from afmdrift.diagnostics import (
        DiagnoseOptions,
        Thresholds,
        diagnose_path,
        diagnosis_text,
        is_run_dir,
    )
    from afmdrift.errors import InputError
    from afmdrift.runs import available_cores, snapshot_store

    if args.burn_in < 0:
        raise InputError(f"--burn-in must be >= 0, got {args.burn_in}")
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    if args.look is not None and args.look < 1:
        raise InputError(f"--look must be >= 1 (the first diagnosis is 1), got {args.look}")
    workers = available_cores() if args.workers is None else args.workers
    config = registration_options(args, load_config(args.config))
    effects = None
    if args.effects is not None:
        effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    thresholds = Thresholds() if args.look is None else Thresholds().at_look(args.look)
    options = DiagnoseOptions(burn_in_frames=args.burn_in, workers=workers, thresholds=thresholds)
    with contextlib.ExitStack() as stack:
        path = args.path
        if args.snapshot:
            if not is_run_dir(path):
                raise InputError(f"--snapshot: {path} is not a run directory (no run.sqlite)")
            path = stack.enter_context(tempfile.TemporaryDirectory(prefix="afmdrift-snapshot-"))
            snapshot_store(args.path, path)
        diagnosis, data = diagnose_path(
            path,
            config=config,
            effects=effects,
            run_dir=args.run_dir,
            session_dir=args.session,
            options=options,
            prior_px=prior_option(args),
        )
        if args.report:  # while a snapshot's directory still exists
            from afmdrift.diagnostics import write_report

            write_report(diagnosis, data, args.report, registration=config.registration)
    if args.json:
        print(json.dumps(diagnosis.to_json(), indent=2))
    else:
        print(diagnosis_text(diagnosis.to_json()))
        if args.report:
            print(f"\nreport: {args.report}")
    return 0
