"""``afmdrift sim record SCENARIO --out DIR``: record a simulated session directory."""

from __future__ import annotations

import argparse
from typing import Any


def register_sim_subcommand(ssub: Any) -> None:
    rec = ssub.add_parser(
        "record",
        help="Record a simulated session directory from a scenario.",
        description="Run SCENARIO (a TOML file or a built-in name such as graphite-paper) "
        "on the simulator's virtual clock, as fast as possible, and write a session "
        "directory (format v1) with frames, channels, events and the true drift "
        "(truth.csv, plus truth_components.csv per physical effect).",
    )
    rec.add_argument("scenario", help="scenario TOML file or built-in scenario name")
    rec.add_argument("--out", required=True, help="session directory to write")
    rec.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    rec.add_argument(
        "--duration-s",
        type=float,
        default=None,
        help="virtual seconds to record (default: the scenario's duration_s)",
    )
    rec.add_argument("--frames", type=int, default=None, help="stop after N frames")
    rec.set_defaults(handler=_record)


def _record(args: argparse.Namespace) -> int:
    from afmdrift.drivers.sim._record import record_session
    from afmdrift.errors import AfmdriftError, InputError

    try:
        summary = record_session(
            args.scenario,
            args.out,
            seed=args.seed,
            duration_s=args.duration_s,
            frames=args.frames,
        )
    except ValueError as err:
        if isinstance(err, AfmdriftError):
            raise
        raise InputError(str(err)) from None
    except OSError as err:
        raise InputError(f"--out {args.out}: cannot write the session: {err.strerror}") from None
    s = summary.stats
    print(
        f"{summary.path}: {summary.frames} frames over {summary.duration_s:.0f} s "
        f"(recorded in {summary.wall_s:.1f} s)"
    )
    if "mean_speed_nm_per_s" in s:
        print(
            f"drift: mean speed {s['mean_speed_nm_per_s']:.3f} nm/s, excursion "
            f"{s['excursion_nm']:.1f} nm, RMS frame step {s['rms_frame_step_nm']:.2f} nm, "
            f"max frame step {s['max_frame_step_nm']:.2f} nm"
        )
    return 0
