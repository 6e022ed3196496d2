"""Is a track ever confidently wrong? Every frame size, every scenario, default configuration.

The track of a session (``afmdrift measure STACK``, ``batch``, ``correct``:
:func:`afmdrift.runs.track_session`) under the default configuration, on

* the simulator: every scenario of ``config/scenarios/hidden/``, its scan
  size kept and its pixel count set to 64, 96, 128, 200, 256 and 512 px, with the
  scenario's offset moves and three more of 40–160 nm per axis (among them
  the (−120, +130) nm of issue 37), logged in the event log, made but not
  logged (a user's folder of images has no event log), or with none;
* the second generator (:func:`afmdrift.testing.generate_track`: rough,
  terraced and particle samples, rigid frames, its own drift shape), with
  its three moves logged, unlogged, or none;

at ``--seeds`` seeds each. An accepted increment (the image position's
change between two accepted frames) is *wrong* when, on either axis, it
misses the truth by more than max(1 px, 3σ), σ the increment's own. Prints
one row per source and frame size: increments accepted, wrong, frames
refused (their share), and each wrong increment. Exit status 1 if any
increment is wrong.

    PYTHONPATH=. .venv/bin/python benchmarks/track_sweep.py [--seeds 3] [--jobs 2]
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HIDDEN = ROOT / "config" / "scenarios" / "hidden"
SIZES = (64, 96, 128, 200, 256, 512)
#: Offset moves: logged in the session's event log, made but not logged, none.
MOVES = ("logged", "unlogged", "none")
#: Frames per simulated session (a frame every scenario frame period).
SIM_FRAMES = 40
#: Frames per generated session.
GEN_FRAMES = 40
#: Offset moves added to a scenario (fractions of the session, nm): the first
#: is the move after which issue 37's batch went 300 nm off.
EXTRA_MOVES = ((0.35, -120.0, 130.0), (0.6, 90.0, 70.0), (0.8, -60.0, -150.0))


@dataclass
class Cell:
    """Counts of one source at one frame size."""

    increments: int = 0
    wrong: int = 0
    frames: int = 0
    refused: int = 0
    sessions: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    def add(self, other: Cell) -> None:
        self.increments += other.increments
        self.wrong += other.wrong
        self.frames += other.frames
        self.refused += other.refused
        self.sessions += other.sessions
        self.seconds += other.seconds
        self.notes += other.notes


def _sim_session(name: str, size: int, seed: int, moves: bool, tmp: Path) -> object:
    from afmdrift.drivers.sim import load_scenario
    from afmdrift.drivers.sim._record import record_session
    from afmdrift.session import read_session

    sc = load_scenario(HIDDEN / f"{name}.toml")
    period = sc.scan.frame_period_s
    duration = SIM_FRAMES * period
    doc = sc.model_dump()
    doc["scan"]["pixels"] = [size, size]
    doc["duration_s"] = duration
    kept = [m for m in doc["offset_moves"] if m["t_s"] < duration] if moves else []
    if moves:
        for frac, x, y in EXTRA_MOVES:
            # between two frames' scans, as a re-centring move is made
            k = int(frac * SIM_FRAMES)
            kept.append({"t_s": k * period - 0.25 * period, "x_nm": x, "y_nm": y})
    doc["offset_moves"] = kept
    scenario = type(sc).model_validate(doc)
    out = tmp / f"{name}-{size}-{seed}-{int(moves)}"
    record_session(scenario, out, seed=seed)
    return read_session(out)


def _generated_session(g: object) -> object:
    """The :class:`~afmdrift.session.Session` of a :class:`GeneratedTrack`."""
    from afmdrift.records import ScanDirection
    from afmdrift.session import Session, SessionMeta

    meta = SessionMeta(
        pixel_size_nm=g.pixel_size_nm,  # type: ignore[attr-defined]
        line_time_s=g.line_time_s,  # type: ignore[attr-defined]
        start_time="2026-01-01T00:00:00+00:00",
        source=g.source,  # type: ignore[attr-defined]
    )
    return Session(
        meta=meta,
        frames=g.frames,  # type: ignore[attr-defined]
        frame_times=g.frame_times,  # type: ignore[attr-defined]
        directions=[ScanDirection.UP] * len(g.frames),  # type: ignore[attr-defined]
        events=list(g.events),  # type: ignore[attr-defined]
        truth=g.truth,  # type: ignore[attr-defined]
    )


def _true_image_nm(session: object, t_s: np.ndarray, dirs: list[object]) -> np.ndarray:
    """Image position m(t) relative to frame 0 of a simulated session:
    p − (O − O_0), plus the scan-direction bias of each frame (±b/2)."""
    from afmdrift.model import offset_change_nm
    from afmdrift.records import ScanDirection

    s = session  # a Session
    p = s.truth_at(t_s)  # type: ignore[attr-defined]
    t0 = float(s.frame_times[0].mean())  # type: ignore[attr-defined]
    o = offset_change_nm(t_s, np.full(t_s.size, t0), s.events)  # type: ignore[attr-defined]
    bias = np.asarray(
        s.meta.extra.get("simulator", {}).get("scan_direction_bias_nm", [0.0, 0.0]),  # type: ignore[attr-defined]
        dtype=np.float64,
    )
    sign = np.array([0.5 if d is ScanDirection.UP else -0.5 for d in dirs])
    m = p - o + sign[:, None] * bias[None, :]
    return m - m[0]


def run_one(source: str, size: int, seed: int, moves: str) -> Cell:
    """One session through :func:`track_session`; the cell's counts."""
    from afmdrift.config import load_config
    from afmdrift.runs import track_session

    cell = Cell(sessions=1)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        if source.startswith("gen:"):
            from afmdrift.testing import generate_track

            g = generate_track(
                size_px=size,
                seed=seed,
                frames=GEN_FRAMES,
                moves=moves != "none",
                sample=source[4:],  # type: ignore[arg-type]
            )
            session = _generated_session(g)
            px = np.asarray(g.pixel_size_nm)
            truth_nm = g.image_px * px
        else:
            session = _sim_session(source, size, seed, moves != "none", Path(tmp))
            mids = session.frame_times.mean(axis=1)  # type: ignore[attr-defined]
            truth_nm = _true_image_nm(session, mids, list(session.directions))  # type: ignore[attr-defined]
            px = np.asarray(session.meta.pixel_size_nm)  # type: ignore[attr-defined]
        if moves == "unlogged":
            session.events = []  # type: ignore[attr-defined]
        config = load_config(None)
        prev_k, prev_m = 0, np.zeros(2)
        for doc in track_session(session, config):  # type: ignore[arg-type]
            cell.frames += 1
            if not doc.get("valid"):
                cell.refused += 1
                continue
            k = int(doc["cur_frame"])
            m = np.array([doc["cumulative_dx_nm"], doc["cumulative_dy_nm"]])
            got = m - prev_m
            want = truth_nm[k] - truth_nm[prev_k]
            sig = np.array([doc["sigma_x_nm"], doc["sigma_y_nm"]])
            tol = np.maximum(px, 3.0 * sig)
            cell.increments += 1
            err = np.abs(got - want)
            if np.any(err > tol):
                cell.wrong += 1
                cell.notes.append(
                    f"{source} {size}px seed {seed} moves={moves}: frame {prev_k}->{k} "
                    f"({doc.get('valid_blocks')}/{doc.get('total_blocks')} blocks) got "
                    f"({got[0]:+.1f}, {got[1]:+.1f}) nm, truth ({want[0]:+.1f}, {want[1]:+.1f}) "
                    f"nm, sigma ({sig[0]:.2f}, {sig[1]:.2f}) nm"
                )
            prev_k, prev_m = k, m
    cell.seconds = time.perf_counter() - started
    return cell


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3, help="seeds per source (3)")
    ap.add_argument("--jobs", type=int, default=1, help="sessions at once (1)")
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    ap.add_argument("--only", nargs="+", help="sources to run (scenario names, gen:rough ...)")
    args = ap.parse_args(argv)
    from afmdrift.testing import TRACK_SAMPLES

    sources = [p.stem for p in sorted(HIDDEN.glob("*.toml"))] + [f"gen:{s}" for s in TRACK_SAMPLES]
    if args.only:
        sources = [s for s in sources if s in args.only]
    tasks = [
        (src, size, seed, moves)
        for src in sources
        for size in args.sizes
        for seed in range(1, args.seeds + 1)
        for moves in MOVES
    ]
    cells: dict[tuple[str, int], Cell] = {}
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        for (src, size, _seed, _moves), cell in zip(
            tasks, pool.map(run_one, *zip(*tasks, strict=True)), strict=True
        ):
            cells.setdefault((src, size), Cell()).add(cell)
    print("| source | px | sessions | increments | wrong | frames refused | s |")
    print("|---|---|---|---|---|---|---|")
    total = Cell()
    for (src, size), c in cells.items():
        share = c.refused / c.frames if c.frames else math.nan
        print(
            f"| {src} | {size} | {c.sessions} | {c.increments} | {c.wrong} | "
            f"{c.refused} ({share:.1%}) | {c.seconds:.0f} |"
        )
        total.add(c)
    print(
        f"\nall: {total.sessions} sessions, {total.increments} increments accepted, "
        f"{total.wrong} wrong, {total.refused} of {total.frames} frames refused; "
        f"{time.perf_counter() - t0:.0f} s"
    )
    for note in total.notes:
        print("-", note)
    return 1 if total.wrong else 0


if __name__ == "__main__":
    sys.exit(main())
