"""How long ``afmdrift diagnose`` takes on one 8 h session, re-runs in series and side by side.

Run: ``.venv/bin/python benchmarks/bench_diagnose_time.py [--repeats N]``

The command as a user runs it (a subprocess, imports included), on:

* two 8 h drift logs of ``../shared/validation/drift-logs`` (``none-100``, a
  control, and ``warmup-100``, whose diagnosis re-runs the most candidates),
  with the model ``trend, thermal``;
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
    a = ap.parse_args()
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
        print("recording an 8 h session (gold-manipulation-8h) ...", flush=True)
        _timed(["sim", "record", "gold-manipulation-8h", "--duration-s", "28800",
                "--out", str(root / "session")], root)  # fmt: skip
        cases.append(("session gold-manipulation-8h (replay included)", [str(root / "session")]))
        for label, args in cases:
            walls: dict[int, list[float]] = {1: [], 2: []}
            for _ in range(a.repeats):
                for w in (1, 2):
                    walls[w].append(_timed(["diagnose", *args, "--workers", str(w)], root))
            m1, m2 = statistics.median(walls[1]), statistics.median(walls[2])
            print(f"{label}: --workers 1 {m1:.1f} s [{min(walls[1]):.1f}-{max(walls[1]):.1f}], "
                  f"--workers 2 {m2:.1f} s [{min(walls[2]):.1f}-{max(walls[2]):.1f}], "
                  f"{m1 / m2:.2f}x (target <= 120 s)", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
