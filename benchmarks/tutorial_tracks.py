"""The tutorial's three sessions under the default configuration: does the
track of ``afmdrift batch`` agree with ``afmdrift replay`` at every frame?

Records ``thermal_lag.toml`` and ``pressure.toml`` at seed 5 and
``stage_thermometer.toml`` at seed 1 (docs/tutorial-diagnose.md), runs
``afmdrift batch SESSION`` and ``afmdrift replay SESSION`` as a user does
(subprocesses, no ``--config``), and prints per session the largest
difference of the image position between the two over the frames both
measured, the frames each refused, and what ``replay`` gives with the
tutorial's small-frames configuration (32 px blocks in 96 px windows) beside
the default: mean σ of the positions and mean prediction error.

    PYTHONPATH=. .venv/bin/python benchmarks/tutorial_tracks.py
"""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HIDDEN = ROOT / "config" / "scenarios" / "hidden"
SESSIONS = (("thermal_lag", 5), ("pressure", 5), ("stage_thermometer", 1))
SMALL = "[registration]\nblock_size = 32\nextended_size = 96\n"


def _run(*args: str, cwd: Path) -> str:
    done = subprocess.run(
        [sys.executable, "-m", "afmdrift", *args], cwd=cwd, capture_output=True, text=True
    )
    if done.returncode not in (0, 1):
        raise SystemExit(f"afmdrift {' '.join(args)}: {done.stderr}")
    return done.stdout + done.stderr


def _rows(run: Path) -> list[dict[str, str]]:
    with (run / "measurements.csv").open(encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _stats(rows: list[dict[str, str]]) -> tuple[float, float, int]:
    sig = [float(r["sigma_nm"]) for r in rows[1:] if r["valid"] == "1" and r["sigma_nm"]]
    err = [float(r["pred_error_nm"]) for r in rows if r["pred_error_nm"]]
    refused = sum(r["valid"] != "1" for r in rows)
    return sum(sig) / len(sig), sum(err) / len(err), refused


def main() -> int:
    worst = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        (cwd / "small.toml").write_text(SMALL, encoding="utf-8")
        for name, seed in SESSIONS:
            s = f"s-{name}"
            _run("sim", "record", str(HIDDEN / f"{name}.toml"), "--out", s, "--seed", str(seed),
                 cwd=cwd)  # fmt: skip
            _run("batch", s, "--out", f"b-{name}", "--workers", "1", cwd=cwd)
            _run("replay", s, "--out", f"r-{name}", cwd=cwd)
            _run("replay", s, "--out", f"q-{name}", "--config", "small.toml", cwd=cwd)
            want = {
                int(r["frame"]): (float(r["image_x_nm"]), float(r["image_y_nm"]))
                for r in _rows(cwd / f"r-{name}")
                if r["valid"] == "1" and r["image_x_nm"]
            }
            lines = (cwd / f"b-{name}" / s / "track.jsonl").read_text().splitlines()
            diffs, refused = [], 0
            for doc in map(json.loads, lines):
                if not doc["valid"]:
                    refused += 1
                    continue
                if doc["cur_frame"] in want:
                    x, y = want[doc["cur_frame"]]
                    diffs.append(
                        math.hypot(doc["cumulative_dx_nm"] - x, doc["cumulative_dy_nm"] - y)
                    )
            sig_d, err_d, ref_d = _stats(_rows(cwd / f"r-{name}"))
            sig_s, err_s, ref_s = _stats(_rows(cwd / f"q-{name}"))
            worst = max(worst, max(diffs))
            print(
                f"{name} seed {seed}: batch vs replay over {len(diffs)} frames: max "
                f"{max(diffs):.3g} nm; batch refused {refused}. replay default: mean sigma "
                f"{sig_d:.3f} nm, mean prediction error {err_d:.2f} nm, {ref_d} refused; "
                f"small-frames: {sig_s:.3f} nm, {err_s:.2f} nm, {ref_s} refused"
            )
    print(f"worst difference {worst:.3g} nm")
    return 0 if worst <= 1.0 else 1


if __name__ == "__main__":
    sys.exit(main())
