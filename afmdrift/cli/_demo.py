"""``afmdrift demo``: drift measured on a generated frame sequence.

Generates a particle texture (gold-colloid-like bumps, 2 nm pixels, 512×512
frames) drifting along a known smooth path, adds height noise at SNR 10, runs
:class:`~afmdrift.registration.DriftTracker` over the frames and prints true
and measured cumulative drift per frame, then the RMS error.
"""

from __future__ import annotations

import argparse
from typing import Any

#: Pixel size of the generated frames (nm).
PIXEL_NM = 2.0


def register(sub: Any) -> None:
    p = sub.add_parser(
        "demo",
        help="Measure drift on a generated frame sequence and compare with the truth.",
        description="Generate frames of a particle sample drifting along a known smooth path "
        "(thermal settling plus a slow creep, SNR 10), track them with the block "
        "phase-correlation engine and print true vs measured cumulative drift.",
    )
    p.add_argument("--frames", type=int, default=20, help="number of frames (default 20)")
    p.add_argument("--size", type=int, default=512, help="frame edge in px (default 512)")
    p.add_argument("--snr", type=float, default=10.0, help="height SNR (default 10)")
    p.add_argument("--seed", type=int, default=2008, help="random seed (default 2008)")
    p.set_defaults(handler=_demo)


def drift_path_nm(t_s: Any) -> Any:
    """Demo drift path (x, y) in nm at times ``t_s``: exponential thermal
    settling (60 nm and -35 nm, time constant 1500 s) plus a linear creep."""
    import numpy as np

    t = np.asarray(t_s, dtype=np.float64)
    settle = 1.0 - np.exp(-t / 1500.0)
    return np.column_stack([60.0 * settle + 0.004 * t, -35.0 * settle + 0.002 * t])


def _demo(args: argparse.Namespace) -> int:
    import math

    import numpy as np

    from afmdrift.errors import InputError
    from afmdrift.registration import DriftTracker
    from afmdrift.testing import TextureShifter, add_noise, particle_texture

    if args.frames < 2:
        raise InputError(f"--frames must be at least 2, got {args.frames}")
    if not 64 <= args.size <= 2048:
        raise InputError(f"--size must be between 64 and 2048 px, got {args.size}")
    if not args.snr > 0:
        raise InputError(f"--snr must be > 0, got {args.snr}")
    rng = np.random.default_rng(args.seed)
    t_s = 256.0 * np.arange(args.frames)  # one frame every 256 s, as in the paper
    path_px = drift_path_nm(t_s) / PIXEL_NM
    margin = math.ceil(float(np.abs(path_px).max())) + 16
    edge = args.size + 2 * margin
    shifter = TextureShifter(particle_texture((edge, edge), pixel_size_nm=PIXEL_NM, rng=rng))
    tracker = DriftTracker(pixel_size_nm=PIXEL_NM)

    print(
        f"afmdrift demo: {args.frames} frames of {args.size}x{args.size} px at {PIXEL_NM:g} nm/px, "
        f"particle sample, SNR {args.snr:g}, one frame per 256 s"
    )
    header = (
        f"{'frame':>5} {'t_s':>6} {'true_x_nm':>10} {'true_y_nm':>10} {'meas_x_nm':>10} "
        f"{'meas_y_nm':>10} {'err_nm':>7} {'blocks':>7}"
    )
    print(header)
    errors: list[float] = []
    origin = path_px[0]
    for i in range(args.frames):
        d = path_px[i] - origin
        frame = shifter.crop((args.size, args.size), dx_px=float(d[0]), dy_px=float(d[1]))
        step = tracker.update(add_noise(frame, snr=args.snr, rng=rng))
        true_nm = d * PIXEL_NM
        if step is None:
            print(f"{i:5d} {t_s[i]:6.0f} {0.0:10.2f} {0.0:10.2f} {'reference':>21}")
            continue
        meas = step.position_nm
        blocks = f"{step.measurement.valid_blocks}/{step.measurement.total_blocks}"
        if step.accepted:
            err = math.hypot(meas[0] - true_nm[0], meas[1] - true_nm[1])
            errors.append(err)
            err_text = f"{err:7.3f}"
        else:
            err_text = f"{'-':>7}"
        print(
            f"{i:5d} {t_s[i]:6.0f} {true_nm[0]:10.2f} {true_nm[1]:10.2f} {meas[0]:10.2f} "
            f"{meas[1]:10.2f} {err_text} {blocks:>7}"
            + ("" if step.accepted else f"  rejected: {step.measurement.reason}")
        )
    rms = math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else math.nan
    print(
        f"RMS error of cumulative drift: {rms:.3f} nm ({rms / PIXEL_NM:.4f} px) over "
        f"{len(errors)} measured frames; {args.frames - 1 - len(errors)} rejected"
    )
    return 0
