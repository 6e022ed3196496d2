"""How long ``afmdrift diagnose`` takes on one 8 h session, re-runs in series and side by side.

Run: ``.venv/bin/python benchmarks/bench_diagnose_time.py [--repeats N]``

The command as a user runs it (a subprocess, imports included), on:

* two 8 h drift logs of ``../shared/validation/drift-logs`` (``none-100``, a
  control, and ``warmup-100``, whose diagnosis re-runs the most candidates),
  with the model ``trend, thermal``;
* the real 6.5 h atom-tracking record ``openspm-0368`` of
  ``../shared/data/real/openspm`` (391 points, one a minute, no channel), with
  the default model, as a user with such a log runs it (issue 40: at most
  5 s);
* an 8 h session of the simulator (``afmdrift sim record gold-manipulation-8h``,
  512² frames every 256 s), which diagnose first replays through the
  pipeline (registration included).

Each with ``--workers 1`` (the online re-runs one after the other, as before
they ran side by side) and ``--workers 2`` (this machine's two cores),
alternated, ``--repeats`` times; the median and the spread. The target of
issue 28 is at most two minutes on a 2-core machine. Run it with nothing
else running.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

EXE = [sys.executable, "-m", "afmdrift"]
SHARED = Path(__file__).resolve().parents[2] / "shared" / "validation" / "drift-logs"
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "openspm"


def _timed(args: list[str], cwd: Path) -> float:
    t0 = time.perf_counter()
    done = subprocess.run([*EXE, *args], cwd=cwd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"afmdrift {' '.join(args)} failed:\n{done.stderr}")
    return wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-session", action="store_true", help="leave out the 8 h simulator session")
    ap.add_argument("--workers-list", default="1,2", help="--workers values timed, e.g. 1")
    a = ap.parse_args()
    counts = [int(w) for w in a.workers_list.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        cases: list[tuple[str, list[str]]] = []
        for name in ("none-100", "warmup-100"):
            if (SHARED / name).is_dir():
                cases.append(
                    (f"drift log {name}", [str(SHARED / name), "--effects", "trend,thermal"])
                )
            else:
                print(f"skipped {name}: {SHARED} not found")
        if (REAL / "openspm-0368").is_dir():
            cases.append(("real record openspm-0368 (default model)", [str(REAL / "openspm-0368")]))
        else:
            print(f"skipped openspm-0368: {REAL} not found")
        if not a.no_session:
            print("recording an 8 h session (gold-manipulation-8h) ...", flush=True)
            _timed(["sim", "record", "gold-manipulation-8h", "--duration-s", "28800",
                    "--out", str(root / "session")], root)  # fmt: skip
            cases.append(
                ("session gold-manipulation-8h (replay included)", [str(root / "session")])
            )
        for label, args in cases:
            walls: dict[int, list[float]] = {w: [] for w in counts}
            for _ in range(a.repeats):
                for w in counts:
                    walls[w].append(_timed(["diagnose", *args, "--workers", str(w)], root))
            line = ", ".join(
                f"--workers {w} {statistics.median(v):.1f} s [{min(v):.1f}-{max(v):.1f}]"
                for w, v in walls.items()
            )
            print(f"{label}: {line}", flush=True)


if __name__ == "__main__":
    main()
