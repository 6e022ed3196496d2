"""Lattice shifts of issue 29: is a valid result ever a lattice period off?

Known shifts of the real NanoScope frame (``../shared/data/real``, a lattice
of period about 10.3 px): 224² crops, the integer part of the shift by the
crop, the fraction by a Fourier shift, white noise at SNR 5–10 on both
frames. Shifts of half a period and of a whole period (10.3 px) in random
directions, ±0.5 px. Prints every valid result more than 0.5 px off and the
counts (valid, off, refused) per group. The pairs are built in
``tests/unit/_lattice_pairs.py``, whose tests measure some of them.

    PYTHONPATH=. .venv/bin/python benchmarks/lattice_shifts.py [--pairs N]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "unit"))

from _lattice_pairs import GROUPS, NANOSCOPE_PERIOD_PX, shifted_pairs

from afmdrift.io import load_image
from afmdrift.registration import measure_drift

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=30, help="pairs per group (30)")
    args = ap.parse_args(argv)
    path = REAL / "nanoscope3a_15um.002"
    if not path.is_file():
        print(f"not run: {path} not found")
        return 0
    img = load_image(str(path))
    px = float(img.pixel_size_nm[0])
    counts = {label: [0, 0, 0] for label, _ in GROUPS}  # valid, off, refused
    pairs = shifted_pairs(img.heights_nm, period_px=NANOSCOPE_PERIOD_PX, pairs=args.pairs)
    for label, _k, d, ref, cur in pairs:
        r = measure_drift(ref, cur, pixel_size_nm=px)
        if not r.valid:
            counts[label][2] += 1
            continue
        counts[label][0] += 1
        err = math.hypot(r.dx_px - d[0], r.dy_px - d[1])
        if err > 0.5:
            counts[label][1] += 1
            print(
                f"- {label}: truth ({d[0]:.2f}, {d[1]:.2f}) px, valid ({r.dx_px:.2f}, "
                f"{r.dy_px:.2f}) px, error {err:.2f} px, sigma {r.sigma_nm / px:.3f} px, "
                f"lattice_px {list(r.lattice_px)}"
            )
    for label, (valid, off, refused) in counts.items():
        print(f"{label}: {args.pairs} pairs, {valid} valid, {off} off, {refused} refused")
    return 0 if all(c[1] == 0 for c in counts.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
