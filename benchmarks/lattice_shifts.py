"""Lattice shifts of issue 29: is a valid result ever a lattice period off?

Known shifts of the real NanoScope frame (``../shared/data/real``, a lattice
of period about 10.3 px): 224² crops, the integer part of the shift by the
crop, the fraction by a Fourier shift, white noise at SNR 5–10 on both
frames. Shifts of half a period and of a whole period (10.3 px) in random
directions, ±0.5 px. Prints every valid result more than 0.5 px off and the
counts (valid, off, refused) per group.

    PYTHONPATH=. .venv/bin/python benchmarks/lattice_shifts.py [--pairs N]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from afmdrift.io import load_image
from afmdrift.registration import measure_drift
from afmdrift.testing import add_noise, fourier_shift

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"
PERIOD_PX = 10.3


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=30, help="pairs per group (30)")
    args = ap.parse_args(argv)
    path = REAL / "nanoscope3a_15um.002"
    if not path.is_file():
        print(f"not run: {path} not found")
        return 0
    img = load_image(str(path))
    h0 = img.heights_nm - img.heights_nm.mean()
    px = float(img.pixel_size_nm[0])
    rng = np.random.default_rng(2)
    wrong = 0
    for label, scale in (("half a period", 0.5), ("a whole period", 1.0)):
        valid = off = refused = 0
        for _ in range(args.pairs):
            angle = rng.uniform(0, 2 * math.pi)
            d = scale * PERIOD_PX * np.array([math.cos(angle), math.sin(angle)])
            d += rng.uniform(-0.5, 0.5, 2)
            ix, iy = round(d[0]), round(d[1])
            h = fourier_shift(h0, dx_px=d[0] - ix, dy_px=d[1] - iy)
            m, n = 16, 224
            ref = h0[m : m + n, m : m + n]
            cur = h[m - iy : m - iy + n, m - ix : m - ix + n]
            snr = rng.uniform(5, 10)
            r = measure_drift(
                add_noise(ref, snr=snr, rng=rng), add_noise(cur, snr=snr, rng=rng), pixel_size_nm=px
            )
            if not r.valid:
                refused += 1
                continue
            valid += 1
            err = math.hypot(r.dx_px - d[0], r.dy_px - d[1])
            if err > 0.5:
                off += 1
                print(
                    f"- {label}: truth ({d[0]:.2f}, {d[1]:.2f}) px, valid ({r.dx_px:.2f}, "
                    f"{r.dy_px:.2f}) px, error {err:.2f} px, sigma {r.sigma_nm / px:.3f} px, "
                    f"lattice_px {list(r.lattice_px)}"
                )
        wrong += off
        print(f"{label}: {args.pairs} pairs, {valid} valid, {off} off, {refused} refused")
    return 0 if wrong == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
