"""``afmdrift evaluate SESSION``: compare drift predictors on a recorded session.

Runs the registration engine over the session's frames (as the service does),
removes commanded offset moves, then replays the drift positions through each
predictor side by side and prints, per predictor, the one-step prediction
error, the continuous-offset error against ``truth.csv`` (when present) for
the Hermite and sinc reconstructions, and the time per frame. ``--json``
prints the report documented in ``docs/model.md``.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import TYPE_CHECKING, Any

from afmdrift.cli._options import add_registration_options, registration_options

if TYPE_CHECKING:
    from afmdrift.session import DriftLog, Session


def register(sub: Any) -> None:
    p = sub.add_parser(
        "evaluate",
        help="Compare drift predictors on a session directory or a drift log.",
        description="Measure every frame of SESSION with the registration engine, convert "
        "to drift positions (commanded offset moves removed), or read the positions of a "
        "drift log (a folder with positions.csv, docs/session-format.md), run each "
        "predictor frame by "
        "frame and report one-step prediction errors (nm), the error of the continuous "
        "offset d(t) against truth.csv when present, and time per frame. Predictors: "
        "last_value, constant_velocity, kalman, kalman_ca, nn, physics, physics_nn.",
    )
    p.add_argument(
        "session", metavar="SESSION|LOG", help="session directory (format v1) or drift log folder"
    )
    p.add_argument(
        "--predictors",
        metavar="A,B,...",
        help="comma-separated predictor names (default: [model] evaluate)",
    )
    p.add_argument("--config", metavar="FILE", help="TOML config (default config/default.toml)")
    p.add_argument(
        "--skip",
        type=int,
        default=2,
        metavar="N",
        help="score one-step errors from the N-th valid frame on (N >= 1, default 2; "
        "the session needs N + 1 valid frames)",
    )
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    add_registration_options(p)
    p.set_defaults(handler=_evaluate)


def _evaluate(args: argparse.Namespace) -> int:
    from afmdrift.config import load_config
    from afmdrift.errors import ConfigError, TooFewFramesError
    from afmdrift.model import FIRST_SCORED_FRAME, PREDICTOR_NAMES, evaluate_series
    from afmdrift.runs import measure_session, series_from_drift_log
    from afmdrift.session import is_drift_log, read_drift_log, read_session

    config = registration_options(args, load_config(args.config))
    names = (
        [n.strip() for n in args.predictors.split(",") if n.strip()]
        if args.predictors
        else list(config.model.evaluate)
    )
    unknown = [n for n in names if n not in PREDICTOR_NAMES]
    if unknown or not names:
        raise ConfigError(
            f"--predictors: unknown name(s) {', '.join(map(repr, unknown)) or '(none given)'} "
            f"(known: {', '.join(PREDICTOR_NAMES)})"
        )
    if args.skip < FIRST_SCORED_FRAME:
        # a predictor predicts only from an observation: valid frame 0 is its first
        raise ConfigError(f"--skip must be >= {FIRST_SCORED_FRAME}, got {args.skip}")
    source: DriftLog | Session
    if is_drift_log(args.session):
        source = read_drift_log(args.session)
        series = series_from_drift_log(source)
    else:
        source = read_session(args.session)
        series = measure_session(source, config)
    try:
        report = evaluate_series(
            source, series, predictors=names, config=config.model, skip=args.skip
        )
    except TooFewFramesError as err:
        raise TooFewFramesError(err.valid, err.needed, str(args.session), err.why) from None
    report["session"] = str(args.session)
    if args.json:
        print(json.dumps(report, indent=2, allow_nan=False, default=_nan_to_none))
    else:
        print(_table(report))
    return 0


def _nan_to_none(value: Any) -> Any:  # pragma: no cover - json only calls it for unknown types
    return None


def _fmt(d: dict[str, Any], axis: str, key: str) -> str:
    v = d.get(axis, {}).get(key, math.nan)
    return f"{v:7.2f}"


def _table(report: dict[str, Any]) -> str:
    lines = [
        f"{report['session']}: {report['frames']} frames ({report['valid_frames']} measured), "
        f"period {report['frame_period_s']:.1f} s; one-step errors from valid frame "
        f"{report['skip']} on",
        f"measurement: {report['measurement']['time_per_frame_ms']['mean']:.0f} ms/frame",
    ]
    if "vs_truth" in report["measurement"]:
        m = report["measurement"]["vs_truth"]
        lines.append(
            f"measurement vs truth (row-mean): mean |e| x {_fmt(m, 'x', 'mean_abs_nm')} "
            f"y {_fmt(m, 'y', 'mean_abs_nm')} nm"
        )
    lines.append("")
    head = (
        f"{'predictor':18s} {'one-step |e| x':>14s} {'y':>7s} {'RMS x':>7s} {'y':>7s} "
        f"{'peak x':>7s} {'y':>7s}"
    )
    if report["truth"]:
        head += f" {'d(t) herm':>9s} {'peak':>7s} {'d(t) sinc':>9s} {'peak':>8s}"
    head += f" {'ms/frame':>9s}"
    lines.append(head)
    for name, r in report["predictors"].items():
        o = r["one_step"]["vs_measured"]
        row = (
            f"{name:18s} {_fmt(o, 'x', 'mean_abs_nm'):>14s} {_fmt(o, 'y', 'mean_abs_nm')} "
            f"{_fmt(o, 'x', 'rms_nm')} {_fmt(o, 'y', 'rms_nm')} "
            f"{_fmt(o, 'x', 'peak_nm')} {_fmt(o, 'y', 'peak_nm')}"
        )
        if report["truth"]:
            c = r["continuous"]
            row += (
                f" {_fmt(c['hermite'], 'pooled', 'mean_abs_nm'):>9s}"
                f" {_fmt(c['hermite'], 'pooled', 'peak_nm')}"
                f" {_fmt(c['sinc'], 'pooled', 'mean_abs_nm'):>9s}"
                f" {_fmt(c['sinc'], 'pooled', 'peak_nm'):>8s}"
            )
        row += f" {r['timing_ms']['per_frame_mean']:9.1f}"
        lines.append(row)
    lines.append("")
    lines.append(
        "one-step: prediction at the frame's mid-scan time minus its measurement (nm); "
        "d(t): mean |error| of the continuous offset against truth between frames, "
        "x and y pooled (nm)."
    )
    return "\n".join(lines)
