"""``afmdrift batch INPUT... --out DIR``: re-analyse an archive on Dask."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from afmdrift.batch._jobs import TASKS
from afmdrift.cli._import import add_file_options, pixel_size_option
from afmdrift.cli._options import (
    add_prior_option,
    add_registration_options,
    prior_option,
    registration_options,
)


def register(sub: Any) -> None:
    p = sub.add_parser(
        "batch",
        help="Re-analyse many recordings on Dask (this machine or a cluster).",
        description="Run a task on every recording (stacks and movies in any format "
        "'afmdrift measure' reads, session directories, globs, folders of images) as "
        "Dask tasks. The single-image files of a folder or glob (a NanoScope series, 2-D "
        ".npy files) are one recording, as 'afmdrift import' would make it. Writes "
        "DIR/<stem>/ (per task, see --task), DIR/summary.csv (one row "
        "per recording, rewritten as each finishes) and DIR/archive.svg. A run started "
        "again skips the recordings done with the same input and configuration. "
        "A recording none of whose frames could be measured has status no_drift and "
        "empty drift columns. --pixel-size-nm serves only the files whose header has no "
        "pixel size. Exit 0: all done; 1: some failed or with no drift measured; 2: usage "
        "error.",
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="recordings, globs or folders")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument(
        "--task",
        choices=TASKS,
        default="measure",
        help="measure (default): the drift track (DIR/<stem>/track.jsonl, the lines of "
        "'afmdrift measure STACK --json'); correct: also the drift-corrected frames "
        "(DIR/<stem>/corrected/frames.npy and an ImageJ corrected.tif); for session "
        "directories, replay: the run directory of 'afmdrift replay' (DIR/<stem>/run); "
        "diagnose: that run and what 'afmdrift diagnose' writes (diagnosis.json, "
        "diagnosis.txt, report.html)",
    )
    add_file_options(p)
    p.add_argument("--config", metavar="FILE", help="TOML config (default config/default.toml)")
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="worker processes of the local cluster (default: one per core)",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="an existing Dask scheduler (tcp://HOST:PORT; default $AFMDRIFT_SCHEDULER, "
        "else a local cluster)",
    )
    add_prior_option(p)
    add_registration_options(p)
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from afmdrift.batch import run_batch
    from afmdrift.config import load_config

    terminal = sys.stderr.isatty() and not os.environ.get("CI")
    report = run_batch(
        args.inputs,
        Path(args.out),
        task=args.task,
        config=registration_options(args, load_config(args.config)),
        workers=args.workers,
        scheduler=args.scheduler,
        pixel_size_nm=pixel_size_option(args.pixel_size_nm, override=args.override_pixel_size),
        override_pixel_size=args.override_pixel_size,
        prior_px=prior_option(args),
        channel=args.channel,
        height_unit=args.height_unit,
        progress=sys.stderr if terminal else None,
    )
    no_drift = [r for r in report.results if r.status == "no_drift"]
    done = len(report.results) - report.failed - len(no_drift)
    print(
        f"{done} done, {len(no_drift)} with no drift measured, {report.failed} failed, "
        f"{report.skipped} skipped as already done: {report.summary}",
        file=sys.stderr,
    )
    for r in report.results:
        if r.status == "failed":
            print(f"failed: {r.error}", file=sys.stderr)
        elif r.status == "no_drift":
            print(f"no drift: {r.recording}: {r.error}", file=sys.stderr)
    return 1 if report.failed or no_drift else 0
