"""Peer test battery of issue 13: one markdown table per peer suite.

Runs every case of ``tests/peers/_battery.py`` (the same cases the tests in
``tests/peers`` run) through ``afmdrift.registration`` and prints, per peer,
case | peer asserts | afmdrift result | verdict, error, σ, reason (or, for
stacks, the frame that decided the verdict), then the
totals. Verdicts: pass / refused (needless when the peer meets its own
assertion) / short (honest σ, misses the peer's tolerance) / fail (a valid
result more than max(0.5 px, 4σ) from the truth: a confident wrong answer).

    PYTHONPATH=. .venv/bin/python benchmarks/peer_battery.py [--json] [--peer NAME]
        [--skip-slow] [--reference]

``--reference`` adds scikit-image's ``phase_cross_correlation`` (upsample 20,
disambiguate) on the same pair as a cross-check of what a peer method does
on our re-created images (its error is taken modulo the frame size, which a
circular correlation cannot tell apart).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "peers"))

import _battery as battery


def _fmt_pair(v: tuple[float, float] | None, digits: int = 3) -> str:
    if v is None:
        return "—"
    return f"({v[0]:.{digits}f}, {v[1]:.{digits}f})"


def _fmt_sigma(v: tuple[float, float] | None) -> str:
    return "—" if v is None else f"({v[0]:.2g}, {v[1]:.2g})"


def _reference(case: battery.Case) -> str:
    """scikit-image's answer on the pair, in afmdrift's sign convention."""
    import numpy as np
    from skimage.registration import phase_cross_correlation

    try:
        data = case.build()
    except battery.MissingDataError:
        return "—"
    if isinstance(data, battery.Stack):
        return "—"
    shift, _, _ = phase_cross_correlation(
        data.reference, data.current, upsample_factor=20, disambiguate=True
    )
    got = (-float(shift[1]), -float(shift[0]))
    if data.truth is None:
        return _fmt_pair(got, 2)
    # A circular correlation knows the shift only modulo the frame size.
    size = np.array(data.reference.shape[::-1], dtype=float)
    d = np.subtract(got, data.truth)
    err = float(np.max(np.abs(d - size * np.round(d / size))))
    return f"{_fmt_pair(got, 2)} err {err:.2f}"


def _why(r: dict[str, Any], limit: int = 240) -> str:
    text = "; ".join(t for t in (r["detail"], r["reason"]) if t)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _row(o: battery.Outcome) -> dict[str, Any]:
    c = o.case
    return {
        "peer": c.peer,
        "case": c.name,
        "source": c.source,
        "peer_asserts": c.asserts,
        "tolerance_px": c.tol_px,
        "tolerance_on_norm": c.tol_norm,
        "note": c.note,
        "peer_succeeds": c.peer_succeeds,
        "realdata": c.realdata,
        "verdict": o.verdict,
        "needless_refusal": o.needless,
        "result_px": o.result_px,
        "error_px": o.error_px,
        "sigma_px": o.sigma_px,
        "reason": o.reason,
        "detail": o.detail,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="machine-readable output")
    ap.add_argument("--peer", action="append", help="only these peers (repeatable)")
    ap.add_argument("--skip-slow", action="store_true", help="leave out cases marked slow")
    ap.add_argument(
        "--reference", action="store_true", help="add scikit-image's answer as a cross-check"
    )
    args = ap.parse_args(argv)

    cases = [
        c
        for c in battery.ALL_CASES
        if (not args.peer or c.peer in args.peer) and not (args.skip_slow and c.slow)
    ]
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for case in cases:
        t = time.perf_counter()
        o = battery.run_case(case)
        row = _row(o)
        row["seconds"] = round(time.perf_counter() - t, 3)
        if args.reference:
            row["skimage_reference"] = _reference(case)
        rows.append(row)
    elapsed = time.perf_counter() - t0

    totals = {v: sum(r["verdict"] == v for r in rows) for v in battery.VERDICTS}
    totals["needless_refusals"] = sum(r["needless_refusal"] for r in rows)
    if args.json:
        json.dump({"cases": rows, "totals": totals, "seconds": elapsed}, sys.stdout, indent=1)
        print()
        return 0

    for peer in dict.fromkeys(r["peer"] for r in rows):
        mine = [r for r in rows if r["peer"] == peer]
        print(f"\n### {peer} — {mine[0]['source'].split()[0]}\n")
        head = "| case | peer asserts | afmdrift (dx, dy) px | verdict | error px | σ px | reason |"
        sep = "|---|---|---|---|---|---|---|"
        if args.reference:
            head += " skimage pcc |"
            sep += "---|"
        print(head)
        print(sep)
        for r in mine:
            verdict = r["verdict"]
            if r["needless_refusal"]:
                verdict = "refused (needless)"
            if verdict in ("fail", "short"):
                verdict = f"**{verdict}**"
            err = "—" if r["error_px"] is None else f"{max(r['error_px']):.3f}"
            line = (
                f"| {r['case']} | {r['peer_asserts']} | {_fmt_pair(r['result_px'])} | "
                f"{verdict} | {err} | {_fmt_sigma(r['sigma_px'])} | "
                f"{_why(r)} |"
            )
            if args.reference:
                line += f" {r['skimage_reference']} |"
            print(line.replace("\n", " "))
        notes = dict.fromkeys(r["note"] for r in mine if r["note"])
        if notes:
            print("\nNotes: " + " ".join(f"({i}) {n}." for i, n in enumerate(notes, 1)))
        sources = dict.fromkeys(r["source"] for r in mine)
        print("Sources: " + "; ".join(sources) + ".")
        skipped = battery.NOT_APPLICABLE.get(peer, [])
        if skipped:
            print("Not re-created: " + "; ".join(skipped) + ".")
    print(
        "\nTotals: "
        + ", ".join(f"{k} {v}" for k, v in totals.items())
        + f" of {len(rows)} cases ({elapsed:.1f} s)"
    )
    worst = [r for r in rows if r["verdict"] == "fail"]
    if worst:
        print("\nConfident wrong answers (valid, error > max(0.5 px, 4σ)):")
        for r in worst:
            print(
                f"- {r['peer']}:{r['case']}: got {_fmt_pair(r['result_px'])}, error "
                f"{_fmt_pair(r['error_px'])} px, σ {_fmt_sigma(r['sigma_px'])} px"
                + (f" ({r['detail']})" if r["detail"] else "")
            )
    return 0 if not worst and math.isfinite(elapsed) else 1


if __name__ == "__main__":
    raise SystemExit(main())
