"""Large shifts, small overlaps (issue 38): two crops of one image whose
overlap is 10–50 % of the frame's area.

Images: natural photographs that ship with scikit-image (retina, the Hubble
deep field, grass, gravel, brick, camera, astronaut; read from the installed
package, never copied) and our own AFM-like textures (rough, particles,
terraces). Per image and overlap share, shifts in every direction (one axis
short and one long, or both alike), with a random sub-pixel part (the large
image moved by a cubic spline first). Per overlap share: found within
0.5 px, refused, and confident wrong answers (valid, more than
max(0.5 px, 4σ) off).

    PYTHONPATH=. .venv/bin/python benchmarks/overlap_sweep.py [--seeds N] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from afmdrift.registration import measure_drift
from afmdrift.testing import particle_texture, rough_texture, terrace_texture

SHARES = (0.10, 0.12, 0.15, 0.20, 0.30, 0.40, 0.50)


def _gray(name: str) -> np.ndarray:
    import skimage.data
    from skimage.color import rgb2gray

    img = np.asarray(getattr(skimage.data, name)(), dtype=np.float64)
    if img.ndim == 3:
        img = rgb2gray(img[..., :3])
    return 100.0 * (img - img.mean()) / (img.std() or 1.0)


def images() -> dict[str, tuple[np.ndarray, int]]:
    """name → (image, frame edge)."""
    rng = np.random.default_rng(3802)
    out: dict[str, tuple[np.ndarray, int]] = {}
    retina = _gray("retina")
    out["retina"] = (retina[250:1150, 250:1150], 450)
    out["hubble"] = (_gray("hubble_deep_field"), 420)
    for name in ("grass", "gravel", "brick", "camera", "astronaut"):
        out[name] = (_gray(name), 256)
    out["rough"] = (
        rough_texture((900, 900), pixel_size_nm=1.0, rng=rng, correlation_length_nm=3.0),
        450,
    )
    out["particles"] = (particle_texture((900, 900), pixel_size_nm=2.0, rng=rng), 450)
    out["terraces"] = (terrace_texture((900, 900), pixel_size_nm=2.0, rng=rng), 450)
    return out


#: Smallest overlap per axis the block engine measures (its smallest image).
MIN_AXIS_PX = 64


def _shift_for(share: float, n: int, rng: np.random.Generator, thin: bool) -> tuple[float, float]:
    """A shift (dx, dy) whose overlap is ``share`` of an n×n frame, both axes
    of the overlap at least :data:`MIN_AXIS_PX` (``thin``: one below it)."""
    # split the share between the axes: (1 - |dx|/n)(1 - |dy|/n) = share
    lo = max(share, MIN_AXIS_PX / n)
    hi = min(1.0, share * n / MIN_AXIS_PX)
    if thin:
        low, high = max(share, 24 / n), (MIN_AXIS_PX - 1) / n
        if low >= high:
            return math.nan, math.nan
        short = rng.uniform(low, high)
        fx, fy = (short, share / short) if rng.random() < 0.5 else (share / short, short)
    elif lo > hi:
        return math.nan, math.nan
    else:
        fx = math.exp(rng.uniform(math.log(lo), math.log(hi)))
        fy = share / fx
    fx, fy = min(fx, 1.0), min(fy, 1.0)
    sx = rng.choice((-1, 1)) * (1 - fx) * n
    sy = rng.choice((-1, 1)) * (1 - fy) * n
    return float(sx), float(sy)


def run(seeds: int) -> list[dict[str, Any]]:
    from scipy.ndimage import shift as spline_shift

    rows: list[dict[str, Any]] = []
    for name, (img, n) in images().items():
        for share in SHARES:
            for seed in range(seeds + THIN_SEEDS):
                thin = seed >= seeds
                rng = np.random.default_rng([3803, seed, int(1000 * share), len(name)])
                sx, sy = _shift_for(share, n, rng, thin)
                if not math.isfinite(sx):
                    continue
                frac = rng.uniform(-0.5, 0.5, 2) if seed % 2 else np.zeros(2)
                ix, iy = round(sx), round(sy)
                big = (
                    img
                    if not frac.any()
                    else spline_shift(img, (frac[1], frac[0]), order=3, mode="reflect")
                )
                # reference at o0, current at o0 - d (a feature at u appears at u + d)
                o0 = (max(0, ix), max(0, iy))
                if (
                    o0[0] + n > img.shape[1]
                    or o0[1] + n > img.shape[0]
                    or o0[0] - ix + n > img.shape[1]
                    or o0[1] - iy + n > img.shape[0]
                ):
                    continue
                ref = img[o0[1] : o0[1] + n, o0[0] : o0[0] + n]
                cur = big[o0[1] - iy : o0[1] - iy + n, o0[0] - ix : o0[0] - ix + n]
                truth = (ix + float(frac[0]), iy + float(frac[1]))
                actual = (n - abs(ix)) * (n - abs(iy)) / (n * n)
                r = measure_drift(ref.copy(), cur.copy(), pixel_size_nm=1.0)
                row: dict[str, Any] = {
                    "image": name, "share": share, "overlap": actual, "seed": seed,
                    "min_axis_px": min(n - abs(ix), n - abs(iy)),
                    "truth_px": list(truth), "valid": bool(r.valid), "reason": r.reason,
                }  # fmt: skip
                if r.valid:
                    err = (abs(r.dx_px - truth[0]), abs(r.dy_px - truth[1]))
                    sig = (r.sigma_x_nm, r.sigma_y_nm)
                    row.update(
                        got_px=[r.dx_px, r.dy_px], err_px=list(err), sigma_px=list(sig),
                        found=max(err) <= 0.5,
                        wrong=any(e > max(0.5, 4 * s) for e, s in zip(err, sig, strict=True)),
                    )  # fmt: skip
                rows.append(row)
    return rows


THIN_SEEDS = 1


def table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| overlap | axes | cases | found ≤ 0.5 px | refused | valid, off > 0.5 px | wrong |",
        "|---|---|---|---|---|---|---|",
    ]
    for share, thin in [(s, t) for t in (False, True) for s in SHARES]:
        cell = [r for r in rows if r["share"] == share and (r["min_axis_px"] < MIN_AXIS_PX) == thin]
        if not cell:
            continue
        ok = [r for r in cell if r["valid"]]
        lines.append(
            f"| {100 * share:.0f} % | {'one < 64 px' if thin else 'both ≥ 64 px'} | {len(cell)} | "
            f"{sum(r['found'] for r in ok)} | "
            f"{len(cell) - len(ok)} | {sum(not r['found'] for r in ok)} | "
            f"{sum(r['wrong'] for r in ok)} |"
        )
    lines.append("")
    lines.append("refused / wrong, by image:")
    for r in rows:
        if not r["valid"] or r.get("wrong") or not r.get("found", True):
            lines.append(
                f"  {r['image']} {100 * r['overlap']:.0f} % (axis {r['min_axis_px']} px) "
                f"truth ({r['truth_px'][0]:+.1f}, "
                f"{r['truth_px'][1]:+.1f}): "
                + (f"got {r['got_px']}" if r["valid"] else f"refused: {r['reason']}")
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    rows = run(args.seeds)
    print(json.dumps(rows) if args.json else table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
