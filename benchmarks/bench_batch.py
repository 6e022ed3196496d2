"""Speed and memory of ``afmdrift batch``, the path users run on an archive.

Run: ``.venv/bin/python benchmarks/bench_batch.py [--recordings N] [--frames M] [--repeats R]``

One archive of ``N`` float32 ``.npy`` movies of ``M`` 512² frames (a rough
texture drifting on a slow path), plus one long movie, the largest file.
Measured side by side in one run, nothing else running:

1. **Throughput of a running cluster**: a ``dask scheduler`` with one, then two
   ``dask worker`` processes (one thread each) on 127.0.0.1, warmed on a small
   archive; ``afmdrift batch --scheduler`` over the archive; frames per
   second, and the ratio two workers / one (the target is ≥ 1.8 on 2 cores).
   Two figures each: the whole command (start-up, connecting, the summary and
   the picture included: about 0.6 s per command), and the
   workers' own (the frames over the busiest worker's time on its
   recordings, from ``summary.csv``), which the command approaches as the
   archive grows; medians of ``--repeats`` runs of the archive. Twice: the
   processes started with Dask's default settings, and with afmdrift's
   (``afmdrift.batch.DASK_SETTINGS``, as ``DASK_...`` variables: what the
   README tells a cluster's owner to set). With each, the CPU the cluster's
   processes take while idle (a floor of what they take from the tasks).
2. **The whole command** as a user runs it with no cluster: ``afmdrift batch
   --workers 1`` and ``--workers 2`` (a LocalCluster started and stopped by
   the command, with afmdrift's settings, its workers' start-up included),
   medians of ``--repeats``; and ``--workers 2`` against ``afmdrift measure``
   run on each recording in turn (the target: the batch takes no longer).
3. **Peak worker memory** on the largest file: the worker's resident
   anonymous memory while it tracks the long movie, against the file's size
   (frames stream from a memory map, so a worker holds a few frames; the
   mapped file pages are page cache, which RSS counts but the kernel reclaims).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import contextlib
import csv
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil

from afmdrift.batch import dask_environ
from afmdrift.testing import TextureShifter, rough_texture
from afmdrift.testing._dask import LoopbackDaskCluster

EXE = [sys.executable, "-m", "afmdrift"]
#: The options every ``afmdrift`` command of the benchmark takes (the movies have no calibration).
COMMON = ["--pixel-size-nm", "2"]


def movie(path: Path, frames: int, seed: int, size: int = 512) -> Path:
    rng = np.random.default_rng(seed)
    tex = rough_texture((size + 160, size + 160), pixel_size_nm=2.0, rng=rng,
                        correlation_length_nm=12.0)  # fmt: skip
    out = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32,
                                    shape=(frames, size, size))  # fmt: skip
    shifter = TextureShifter(tex)
    for k in range(frames):
        a = 2 * np.pi * k / max(frames, 1)
        out[k] = shifter.crop((size, size), dx_px=30 * np.sin(a), dy_px=20 * np.sin(2 * a))
        out[k] += rng.normal(0.0, 0.1, size=(size, size)).astype(np.float32)
    out.flush()
    del out
    return path


def batch(args: list[str], cwd: Path) -> float:
    t0 = time.perf_counter()
    subprocess.run([*EXE, "batch", *args], cwd=cwd, check=False,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    return time.perf_counter() - t0


def warm_up(warm: Path, out: Path, n: int, common: list[str], address: str) -> None:
    """Run the small ``warm`` archive until each of the ``n`` workers has done a
    recording (imported the package, loaded its compiled kernels, planned its
    FFTs), so that no timed run pays a worker's first start."""
    for attempt in range(10):
        dest = out / str(attempt)
        batch([str(warm), "--out", str(dest), *common, "--scheduler", address], out.parent)
        with (dest / "summary.csv").open(newline="", encoding="utf-8") as f:
            if len({row["worker"] for row in csv.DictReader(f)}) >= n:
                return
    raise RuntimeError(f"the warm-up did not reach all {n} workers")


def busiest_worker_s(summary: Path) -> float:
    """The largest sum of ``seconds`` over one worker's recordings in ``summary``."""
    per: dict[str, float] = {}
    with summary.open(newline="", encoding="utf-8") as f:
        for row in csv.DictReader(f):
            per[row["worker"]] = per.get(row["worker"], 0.0) + float(row["seconds"])
    return max(per.values())


def family(p: psutil.Process) -> list[psutil.Process]:
    """``p`` and its children (a nanny and the worker process it started)."""
    return [p, *p.children(recursive=True)]


def anon_mb(p: psutil.Process) -> float:
    """Resident anonymous memory of ``p`` and its children, MB: what the worker
    holds itself. File pages of the memory-mapped stack are left out: they
    count in RSS while mapped but belong to the page cache, which the kernel
    reclaims as it needs."""
    total = 0
    for q in family(p):
        for line in Path(f"/proc/{q.pid}/status").read_text().splitlines():
            if line.startswith("RssAnon:"):
                total += int(line.split()[1])
    return total / 1024


def peak_mb(procs: list[psutil.Process], stop: threading.Event, out: list[float]) -> None:
    peak = 0.0
    while not stop.is_set():
        for p in procs:
            with contextlib.suppress(psutil.Error, OSError):
                peak = max(peak, anon_mb(p))
        time.sleep(0.05)
    out.append(peak)


def running_cluster(
    label: str, env: dict[str, str], arc: Path, warm: Path, root: Path, frames: int, repeats: int
) -> None:
    """Part 1 for one set of Dask settings ``env``: prints both figures and the ratios."""
    fps: dict[int, float] = {}
    busy: dict[int, float] = {}
    for n in (1, 2):
        walls, busiest = [], []
        with LoopbackDaskCluster(n, env=env) as cluster:
            warm_up(warm, root / f"w{label}{n}", n, COMMON, cluster.address)
            idle = idle_cpu(cluster)
            for r in range(repeats):  # a new --out each time: nothing is skipped
                out = root / f"c{label}{n}-{r}"
                walls.append(batch([str(arc), "--out", str(out), *COMMON,
                                    "--scheduler", cluster.address], root))  # fmt: skip
                busiest.append(busiest_worker_s(out / "summary.csv"))
        wall, busy[n] = statistics.median(walls), statistics.median(busiest)
        fps[n] = frames / wall
        print(f"running cluster ({label} settings), {n} worker(s), median of {repeats}: command "
              f"{wall:.2f} s [{min(walls):.2f}-{max(walls):.2f}], {fps[n]:.0f} frames/s; busiest "
              f"worker {busy[n]:.2f} s, {frames / busy[n]:.0f} frames/s; idle, the cluster's "
              f"processes take {idle:.1f} % of a core")  # fmt: skip
    print(f"running cluster ({label} settings), two workers / one: command "
          f"{fps[2] / fps[1]:.2f}x, workers {busy[1] / busy[2]:.2f}x (target >= 1.8)")  # fmt: skip


def idle_cpu(cluster: LoopbackDaskCluster, seconds: float = 5.0) -> float:
    """CPU the scheduler and the workers (nannies and their worker processes)
    use while no task runs, in % of one core, over ``seconds``."""
    procs = [psutil.Process(pid) for pid in [cluster.scheduler_pid, *cluster.worker_pids]]

    def used() -> float:
        total = 0.0
        for p in procs:
            for q in family(p):
                t = q.cpu_times()
                total += t.user + t.system
        return total

    before, t0 = used(), time.perf_counter()
    time.sleep(seconds)
    return 100 * (used() - before) / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recordings", type=int, default=12)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--long-frames", type=int, default=600, help="the largest file's frames")
    ap.add_argument("--repeats", type=int, default=3, help="runs of the archive per cluster")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        arc = root / "arc"
        arc.mkdir()
        for k in range(a.recordings):
            movie(arc / f"m{k:02d}.npy", a.frames, seed=k)
        frames = a.recordings * a.frames
        warm = root / "warm"
        warm.mkdir()
        for k in range(4):  # enough recordings that each worker of two takes one
            movie(warm / f"w{k}.npy", 4, seed=90 + k)
        print(f"archive: {a.recordings} x {a.frames} frames of 512² float32")

        running_cluster("Dask's default", {}, arc, warm, root, frames, a.repeats)
        running_cluster("afmdrift's", dask_environ(), arc, warm, root, frames, a.repeats)

        local: dict[int, float] = {}
        for n in (1, 2):
            walls = [batch([str(arc), "--out", str(root / f"local{n}-{r}"), *COMMON,
                            "--workers", str(n)], root) for r in range(a.repeats)]  # fmt: skip
            local[n] = statistics.median(walls)
            print(f"afmdrift batch --workers {n} (LocalCluster started by the command), median of "
                  f"{a.repeats}: {local[n]:.2f} s [{min(walls):.2f}-{max(walls):.2f}], "
                  f"{frames / local[n]:.0f} frames/s")  # fmt: skip
        print(f"afmdrift batch --workers 2 / --workers 1: {local[1] / local[2]:.2f}x")
        t0 = time.perf_counter()
        for f in sorted(arc.glob("*.npy")):
            subprocess.run([*EXE, "measure", str(f), *COMMON], cwd=root, check=False,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        serial = time.perf_counter() - t0
        print(f"afmdrift measure on each recording in turn: {serial:.2f} s; "
              f"batch --workers 2 / serial {local[2] / serial:.2f} (target <= 1)")  # fmt: skip

        big = movie(root / "long.npy", a.long_frames, seed=123)
        with LoopbackDaskCluster(1) as cluster:
            warm_up(warm, root / "wl", 1, COMMON, cluster.address)
            workers = [psutil.Process(pid) for pid in cluster.worker_pids]
            base = anon_mb(workers[0])
            stop, peak = threading.Event(), []  # type: ignore[var-annotated]
            watcher = threading.Thread(target=peak_mb, args=(workers, stop, peak))
            watcher.start()
            wall = batch([str(big), "--out", str(root / "long"), *COMMON,
                          "--scheduler", cluster.address], root)  # fmt: skip
            stop.set()
            watcher.join()
        size_mb = big.stat().st_size / 2**20
        print(f"largest file: {size_mb:.0f} MB ({a.long_frames} frames of 512² float32) in "
              f"{wall:.1f} s; worker's anonymous resident memory {base:.0f} MB idle, "
              f"peak {peak[0]:.0f} MB (+{peak[0] - base:.0f} MB)")  # fmt: skip


if __name__ == "__main__":
    main()
