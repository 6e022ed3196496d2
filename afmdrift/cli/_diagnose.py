"""``afmdrift diagnose RUN_DIR|SESSION``: model against measurement."""

from __future__ import annotations

import argparse
import json
from typing import Any


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
    p.set_defaults(handler=_diagnose)


def _diagnose(args: argparse.Namespace) -> int:
    from afmdrift.config import load_config
    from afmdrift.diagnostics import DiagnoseOptions
    from afmdrift.diagnostics._run import diagnose_path
    from afmdrift.errors import InputError

    if args.burn_in < 0:
        raise InputError(f"--burn-in must be >= 0, got {args.burn_in}")
    config = load_config(args.config)
    effects = None
    if args.effects is not None:
        effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    diagnosis, data = diagnose_path(
        args.path,
        config=config,
        effects=effects,
        run_dir=args.run_dir,
        session_dir=args.session,
        options=DiagnoseOptions(burn_in_frames=args.burn_in),
    )
    if args.report:
        from afmdrift.diagnostics import write_report

        write_report(diagnosis, data, args.report, registration=config.registration)
    if args.json:
        print(json.dumps(diagnosis.to_json(), indent=2))
    else:
        print(format_text(diagnosis.to_json()))
        if args.report:
            print(f"\nreport: {args.report}")
    return 0


def _f(v: Any, fmt: str = ".2f") -> str:
    return "-" if v is None else format(v, fmt)


def format_text(j: dict[str, Any]) -> str:
    """Human-readable summary of the JSON object."""
    lines = [
        f"model: {', '.join(j['model_effects'])} "
        f"(active: {', '.join(j['active_effects']) or 'none'})",
        f"frames: {j['frames']} fed, first {j['burn_in_frames']} left out of the statistics",
        f"one-step error: RMS {_f(j['rmse_nm'])} nm (x {_f(j['rmse_x_nm'])}, "
        f"y {_f(j['rmse_y_nm'])}), mean |e| {_f(j['mean_abs_error_nm'])} nm, "
        f"peak {_f(j['peak_error_nm'])} nm",
    ]
    if j["truth"] is not None:
        t = j["truth"]
        lines.append(
            f"continuous prediction vs true drift: RMS {_f(t['rmse_nm'])} nm, "
            f"mean |e| {_f(t['mean_abs_error_nm'])} nm, peak {_f(t['peak_error_nm'])} nm"
        )
    lb = j["ljung_box"]
    lines.append(
        "Ljung-Box whiteness p-value: "
        + ", ".join(f"{a} {_f(lb[a]['p_value'], '.2g')}" for a in ("x", "y"))
    )
    for pat in j["patterns"]:
        lines.append(f"pattern: {pat}")
    if j["failures"]:
        lines.append("where it fails:")
        for f in j["failures"]:
            lines.append(f"  {f['t_start_s']:8.0f}-{f['t_end_s']:.0f} s  {f['note']}")
    else:
        lines.append("where it fails: no failure episode found")
    lines.append(
        "candidates (rank, effect, significant, ΔAICc, change of the cross-validated "
        "error, one-step RMS with it):"
    )
    width = max([15, *(len(c["effect"]) for c in j["candidates"])])
    for c in j["candidates"]:
        if not c["testable"]:
            lines.append(f"  {c['rank']:2d}. {c['effect']:<{width}} not testable: {c['reason']}")
            continue
        cv = "-" if c["cv_drop"] is None else f"{-100 * c['cv_drop']:+.0f}%"
        kind = "" if c["rmse_after_kind"] != "cv_estimate" else " (est.)"
        lines.append(
            f"  {c['rank']:2d}. {c['effect']:<{width}} {'YES' if c['significant'] else 'no ':<4} "
            f"{_f(c['delta_aicc'], '8.1f')} {cv:>7} "
            f"{'-' if c['rmse_after_nm'] is None else _f(c['rmse_after_nm']) + ' nm'}{kind}"
        )
    lines.append("")
    lines.append(j["finding"])
    if j["after"] is not None:
        a = j["after"]
        lines.append("")
        lines.append("before / after (one-step error, nm):")
        lines.append(f"  {'':<8}{'RMS':>8}{'mean|e|':>9}{'peak':>8}  effects")
        lines.append(
            f"  {'before':<8}{_f(j['rmse_nm'], '8.2f')}{_f(j['mean_abs_error_nm'], '9.2f')}"
            f"{_f(j['peak_error_nm'], '8.2f')}  {', '.join(j['model_effects'])}"
        )
        lines.append(
            f"  {'after':<8}{_f(a['rmse_nm'], '8.2f')}{_f(a['mean_abs_error_nm'], '9.2f')}"
            f"{_f(a['peak_error_nm'], '8.2f')}  {', '.join(a['effects'])}"
        )
    if j["config"]:
        lines.append("")
        lines.append(j["config"])
    return "\n".join(lines)
