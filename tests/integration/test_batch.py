"""``afmdrift batch`` against a real Dask cluster: a ``dask scheduler`` and two
``dask worker`` processes started from this venv on 127.0.0.1, the command run
as a user runs it (a subprocess with ``--scheduler``)."""

from __future__ import annotations

import csv
import json
import math
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from afmdrift.config import AfmdriftConfig
from afmdrift.io import load_stack
from afmdrift.runs import track_stack
from afmdrift.testing import rough_texture, shifted_crop
from afmdrift.testing._dask import LoopbackDaskCluster

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]


def _movie(path: Path, seed: int, frames: int = 8, size: int = 128) -> Path:
    rng = np.random.default_rng(seed)
    tex = rough_texture((size + 200, size + 200), pixel_size_nm=1.0, rng=rng,
                        correlation_length_nm=4.0)  # fmt: skip
    step = rng.uniform(-0.8, 0.8, size=2)
    stack = [
        shifted_crop(tex, shape=(size, size), dx_px=step[0] * k, dy_px=step[1] * k)
        for k in range(frames)
    ]
    np.save(path, np.asarray(stack, dtype=np.float32))
    return path


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """A ``dask scheduler`` and two ``dask worker`` processes on loopback."""
    with LoopbackDaskCluster(2) as cluster:
        yield cluster.address


def _batch(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "afmdrift", "batch", *args],
        cwd=cwd, capture_output=True, text=True, timeout=240,
    )  # fmt: skip


def _summary(out: Path) -> dict[str, dict[str, str]]:
    with (out / "summary.csv").open(encoding="utf-8") as fh:
        return {row["recording"]: row for row in csv.DictReader(fh)}


def _same(a: object, b: object) -> bool:
    """Equal documents, floats within 1e-6."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float):
        return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= 1e-6
    return a == b


def test_batch_on_a_cluster_equals_measure_and_reports_a_bad_file(
    scheduler: str, tmp_path: Path
) -> None:
    arc = tmp_path / "arc"
    arc.mkdir()
    movies = [_movie(arc / f"m{k}.npy", seed=k) for k in range(3)]
    good = movies[0].read_bytes()
    (arc / "cut.npy").write_bytes(good[: len(good) // 3])  # a truncated file
    out = tmp_path / "out"
    done = _batch(str(arc / "*.npy"), "--out", str(out), "--pixel-size-nm", "1",
                  "--scheduler", scheduler, cwd=tmp_path)  # fmt: skip
    assert done.returncode == 1, done.stderr
    rows = _summary(out)
    assert set(rows) == {str(p) for p in [*movies, arc / "cut.npy"]}
    cut = rows[str(arc / "cut.npy")]
    assert cut["status"] == "failed"
    assert "cut.npy" in cut["error"]
    assert "\n" not in cut["error"]
    workers = {rows[str(m)]["worker"] for m in movies}
    assert all(w.startswith("tcp://127.0.0.1:") for w in workers)
    for m in movies:
        row = rows[str(m)]
        assert row["status"] == "done"
        serial = list(track_stack(load_stack(m, pixel_size_nm=(1.0, 1.0)), AfmdriftConfig()))
        lines = [json.loads(x) for x in (out / m.stem / "track.jsonl").read_text().splitlines()]
        assert _same(lines, serial), m
        assert int(row["frames"]) == len(serial) + 1
        last = [d for d in serial if d["valid"]][-1]
        assert float(row["drift_x_nm"]) == pytest.approx(last["cumulative_dx_nm"], abs=1e-6)
        assert float(row["drift_y_nm"]) == pytest.approx(last["cumulative_dy_nm"], abs=1e-6)
    assert (out / "archive.svg").stat().st_size > 0


def test_a_batch_killed_with_sigkill_redoes_nothing_that_was_done(
    scheduler: str, tmp_path: Path
) -> None:
    arc = tmp_path / "arc"
    arc.mkdir()
    movies = [_movie(arc / f"m{k:02d}.npy", seed=10 + k, frames=30) for k in range(10)]
    out = tmp_path / "out"
    args = [str(arc), "--out", str(out), "--pixel-size-nm", "1", "--scheduler", scheduler]
    proc = subprocess.Popen(
        [sys.executable, "-m", "afmdrift", "batch", *args],
        cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        for _ in range(1200):
            results = list(out.glob("*/result.json"))
            if len(results) >= 2:
                break
            assert proc.poll() is None, "the batch ended before it could be killed"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    time.sleep(3.0)  # a task running when its client died may still finish on its worker
    before = {p.parent.name: p.stat().st_mtime_ns for p in out.glob("*/result.json")}
    assert 2 <= len(before) < len(movies), "kill the batch while it runs"
    again = _batch(*args, cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert f"{len(before)} of {len(movies)} recordings already done" in again.stderr
    after = {p.parent.name: p.stat().st_mtime_ns for p in out.glob("*/result.json")}
    assert set(after) == {m.stem for m in movies}
    assert all(after[k] == t for k, t in before.items()), "a done recording was redone"
    assert all(r["status"] == "done" for r in _summary(out).values())


def test_a_local_cluster_corrects_into_an_imagej_stack(tmp_path: Path) -> None:
    """No scheduler given: a LocalCluster of two workers; ``--task correct`` writes
    the corrected frames as a TIFF stack that Fiji opens with its pixel size."""
    import tifffile

    movie = _movie(tmp_path / "m.npy", seed=3)
    out = tmp_path / "out"
    done = _batch(str(movie), "--out", str(out), "--pixel-size-nm", "2", "--workers", "2",
                  "--task", "correct", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr
    with tifffile.TiffFile(out / "m" / "corrected.tif") as tif:
        assert tif.is_imagej
        frames = tif.asarray()
        meta = tif.imagej_metadata
        x_res = tif.pages[0].tags["XResolution"].value
    assert frames.shape == (8, 128, 128)
    assert meta is not None
    assert meta["unit"] == "nm"
    assert x_res[1] / x_res[0] == pytest.approx(2.0)  # nm per pixel
    assert (out / "m" / "track.jsonl").is_file()


def test_usage_errors_exit_2(tmp_path: Path) -> None:
    bad = _batch(str(tmp_path / "none-*.npy"), "--out", str(tmp_path / "o"), cwd=tmp_path)
    assert bad.returncode == 2
    assert "matches no file" in bad.stderr
    movie = _movie(tmp_path / "m.npy", seed=4)
    bad = _batch(str(movie), "--out", str(tmp_path / "o"), "--workers", "0", cwd=tmp_path)
    assert bad.returncode == 2
    assert "--workers must be >= 1" in bad.stderr


def test_the_given_pixel_size_serves_only_files_without_one(tmp_path: Path) -> None:
    """``--pixel-size-nm`` applies to the inputs that need it: a bare .npy stack
    takes it, an ImageJ TIFF stack with its own calibration keeps that."""
    import tifffile

    from afmdrift.batch import Job, run_job
    from afmdrift.batch._jobs import fingerprint

    npy = _movie(tmp_path / "bare.npy", seed=5)
    tif = tmp_path / "calibrated.tif"
    tifffile.imwrite(tif, np.load(npy), imagej=True, resolution=(2.0, 2.0),
                     metadata={"axes": "TYX", "unit": "nm"})  # fmt: skip
    config = AfmdriftConfig().model_dump(mode="json")
    drift = {}
    for path in (npy, tif):
        job = Job(recording=str(path), path=str(path), out=str(tmp_path / path.stem),
                  task="measure", config=config, pixel_size_nm=(3.0, 3.0))  # fmt: skip
        result = run_job(Job(**{**{f: getattr(job, f) for f in job.__dataclass_fields__},
                                "key": fingerprint(job)}))  # fmt: skip
        assert result.status == "done", result.error
        drift[path.suffix] = result.drift_x_nm
    # the same frames: the drift in px is the same, in nm it scales with the pixel
    assert drift[".tif"] / drift[".npy"] == pytest.approx(0.5 / 3.0, rel=1e-3)
    bare = Job(recording=str(npy), path=str(npy), out=str(tmp_path / "no-px"),
               task="measure", config=config)  # fmt: skip
    failed = run_job(bare)
    assert failed.status == "failed"
    assert "carries no pixel size" in failed.error
    assert "bare.npy" in failed.error
