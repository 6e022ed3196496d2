"""What the drift trajectory adds to each 512² frame, measured side by side.

Run: ``.venv/bin/python benchmarks/bench_trajectory.py [--frames N]``

A stream of 512×512 frames (a particle texture at SNR 10 whose drift speeds
up and slows down within each 128 s scan: every row is rendered at its own
scan time) goes through the path the daemon takes for positions,
:class:`afmdrift.pipeline.DriftPositions` (registration, block rows placed in
time, causal trajectory update), and, frame by frame in the same run,
through a bare :class:`afmdrift.registration.DriftTracker` on the same images.
Prints the median time per frame of both, their difference (the cost of the
trajectory: target ≤ 1 ms), and the median time of the trajectory update
alone (:meth:`DriftTrajectory.add_frame`).
"""

from __future__ import annotations

import os

# One OpenBLAS thread, as every afmdrift command process runs (afmdrift.cli),
# set before NumPy loads it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import statistics
import time

import numpy as np

from afmdrift.config import AfmdriftConfig
from afmdrift.model import DriftTrajectory
from afmdrift.pipeline import DriftPositions
from afmdrift.records import Frame, ScanDirection
from afmdrift.registration import DriftTracker
from afmdrift.testing import add_noise, particle_texture

SHAPE = (512, 512)
PIXEL_NM = 2.0
LINE_S = 0.25
PERIOD_S = 256.0


def drift_px(t: np.ndarray) -> np.ndarray:
    """A drift whose speed changes within a frame (px)."""
    x = 30.0 * (1 - np.exp(-t / 2500.0)) + 3.0 * np.sin(2 * np.pi * t / 900.0)
    y = -20.0 * (1 - np.exp(-t / 2000.0)) + 2.0 * np.cos(2 * np.pi * t / 700.0)
    return np.column_stack([x, y])


def render(tex: np.ndarray, k: int, rng: np.random.Generator) -> Frame:
    """Frame k with each row read at its scan time (integer shifts: fast)."""
    t0 = k * PERIOD_S
    rows = np.arange(SHAPE[0])
    t = t0 + (rows + 0.5) * LINE_S
    d = np.rint(drift_px(t)).astype(int)
    img = np.empty(SHAPE, np.float32)
    for r in rows:
        y = 64 + r - d[r, 1]
        x0 = 64 - d[r, 0]
        img[r] = tex[y, x0 : x0 + SHAPE[1]]
    img = add_noise(img, snr=10.0, rng=rng).astype(np.float32)
    return Frame(k, img, (PIXEL_NM, PIXEL_NM), t0, t0 + SHAPE[0] * LINE_S, ScanDirection.UP)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    tex = particle_texture((640, 640), pixel_size_nm=PIXEL_NM, rng=rng).astype(np.float32)
    frames = [render(tex, k, rng) for k in range(args.frames)]
    cfg = AfmdriftConfig()
    positions = DriftPositions(config=cfg, keep_trajectory=True)
    tracker = DriftTracker(pixel_size_nm=PIXEL_NM, config=cfg.registration)
    nan2 = np.full(2, np.nan)
    with_traj: list[float] = []
    bare: list[float] = []
    accepted = 0
    for k, frame in enumerate(frames):
        t0 = time.perf_counter()
        tracker.update(frame.heights_nm)
        t1 = time.perf_counter()
        pos = positions.locate(frame, seq=k, events=[], prediction_nm=nan2, n_fed=k, held=False)
        t2 = time.perf_counter()
        if k >= 5:
            bare.append(t1 - t0)
            with_traj.append(t2 - t1)
        accepted += pos.trajectory is not None
    # the trajectory update alone, on the constraints of the same stream
    traj = DriftTrajectory(q_nm2_s3=positions.trajectory.q, window=cfg.model.trajectory_window)
    alone: list[float] = []
    for key in positions.trajectory.order:
        f = positions.trajectory.frames[key]
        t0 = time.perf_counter()
        traj.add_frame(key, f.t_s, sign=f.sign, t_mid_s=f.t_mid_s, constraints=f.constraints)
        alone.append(time.perf_counter() - t0)
    ms = 1e3
    print(f"frames: {args.frames} of {SHAPE[0]}x{SHAPE[1]} px, {accepted} with trajectory samples")
    print(f"DriftTracker.update (bare registration): median {statistics.median(bare) * ms:.2f} ms")
    print(
        f"DriftPositions.locate (registration + trajectory): median "
        f"{statistics.median(with_traj) * ms:.2f} ms"
    )
    print(
        f"difference: {(statistics.median(with_traj) - statistics.median(bare)) * ms:.2f} ms "
        "(target <= 1 ms)"
    )
    print(f"DriftTrajectory.add_frame alone: median {statistics.median(alone[5:]) * ms:.3f} ms")


if __name__ == "__main__":
    main()
