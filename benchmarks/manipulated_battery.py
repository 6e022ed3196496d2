"""Manipulated-frame battery of issue 29: one row per texture and manipulation.

Builds the pairs of ``tests/manipulated/_manipulated_pairs.py`` (the same pairs the
tests in ``tests/manipulated`` measure; textures, manipulations and noise are
described there), measures each with ``measure_drift`` (default
configuration, no prior: the coarse alignment finds the shift, as ``afmdrift
measure`` does) and prints a markdown table: pairs, refused, confident wrong
answers (valid, more than max(0.5 px, 4σ) off), RMS and largest error of the
valid results (both axes pooled), and the mean share of the frame changed;
then the totals and every refusal and wrong answer. Real textures are left
out, with a note, when ``../shared/data/real`` is absent.

    PYTHONPATH=. .venv/bin/python benchmarks/manipulated_battery.py [--pairs N]
        [--texture NAME ...] [--kind NAME ...] [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "manipulated"))

import _manipulated_pairs as battery


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=40, help="pairs per texture and kind (40)")
    ap.add_argument("--texture", action="append", choices=battery.TEXTURES, help="repeatable")
    ap.add_argument("--kind", action="append", choices=list(battery.KINDS), help="repeatable")
    ap.add_argument("--json", action="store_true", help="machine-readable output")
    args = ap.parse_args(argv)

    cells: list[battery.Cell] = []
    bad: list[battery.Outcome] = []
    missing: list[str] = []
    for name in args.texture or battery.TEXTURES:
        try:
            battery.texture(name)
        except battery.MissingDataError as err:
            missing.append(f"{name}: {err}")
            continue
        for kind in args.kind or list(battery.KINDS):
            outcomes = [
                battery.measure(battery.make_pair(name, kind, seed)) for seed in range(args.pairs)
            ]
            cells.append(battery.Cell.of(outcomes))
            bad.extend(o for o in outcomes if not o.valid or o.wrong)
            if not args.json:
                print(f"  {name}/{kind} done", file=sys.stderr, flush=True)

    pairs = sum(c.pairs for c in cells)
    refused = sum(c.refused for c in cells)
    wrong = sum(c.wrong for c in cells)
    if args.json:
        doc = {
            "cells": [dataclasses.asdict(c) for c in cells],
            "pairs": pairs,
            "refused": refused,
            "wrong": wrong,
            "problems": [o.describe() for o in bad],
            "missing": missing,
        }
        json.dump(doc, sys.stdout, indent=1)
        print()
    else:
        print("| texture | manipulation | changed | pairs | refused | wrong | RMS px | max px |")
        print("|---|---|---|---|---|---|---|---|")
        for c in cells:
            print(
                f"| {c.texture} | {c.kind} | {100 * c.changed:.0f} % | {c.pairs} | "
                f"{c.refused} ({100 * c.refused / c.pairs:.1f} %) | {c.wrong} | "
                f"{c.rms_px:.4f} | {c.max_px:.3f} |"
            )
        share = 100 * refused / pairs if pairs else math.nan
        print(f"\nTotals: {pairs} pairs, {refused} refused ({share:.2f} %), {wrong} wrong.")
        for line in missing:
            print(f"Not run: {line}")
        if bad:
            print("\nRefusals and confident wrong answers:")
            for o in bad:
                print(f"- {o.describe()}")
    return 0 if wrong == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
