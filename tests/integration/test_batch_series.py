"""``afmdrift batch`` on a folder or glob of single-image files: the series is ONE
recording, its frames ordered and timed as ``afmdrift import`` makes them; a
stack beside it stays a recording of its own. Run as a user runs it (a
subprocess, a local cluster of one worker)."""

from __future__ import annotations

import csv
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from service_sim import run_afmdrift

from afmdrift.testing import rough_texture, shifted_crop

pytestmark = pytest.mark.slow

#: Known drift between consecutive single images, px (x, y).
STEP_PX = (0.7, -0.4)
PIXEL_NM = 2.0


def _summary(out: Path) -> dict[str, dict[str, str]]:
    with (out / "summary.csv").open(encoding="utf-8") as fh:
        return {row["recording"]: row for row in csv.DictReader(fh)}


def _track(path: Path) -> list[dict[str, object]]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


def test_a_folder_of_single_npy_images_is_one_recording_beside_a_stack(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    tex = rough_texture((320, 320), pixel_size_nm=1.0, rng=rng, correlation_length_nm=4.0)
    folder = tmp_path / "series"
    folder.mkdir()
    for k in range(4):
        frame = shifted_crop(tex, shape=(128, 128), dx_px=STEP_PX[0] * k, dy_px=STEP_PX[1] * k)
        np.save(folder / f"img_{k:03d}.npy", frame.astype(np.float32))
    stack = [shifted_crop(tex, shape=(128, 128), dx_px=0.5 * k, dy_px=0.0) for k in range(3)]
    np.save(folder / "stack.npy", np.asarray(stack, dtype=np.float32))

    out = tmp_path / "out"
    done = run_afmdrift("batch", "series", "--out", "out", "--workers", "1",
                        "--pixel-size-nm", str(PIXEL_NM), cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr
    rows = _summary(out)
    assert set(rows) == {"series", "series/stack.npy"}
    assert rows["series"]["frames"] == "4"
    assert rows["series"]["valid_frames"] == "3"  # the first is the reference, not measured
    assert rows["series/stack.npy"]["frames"] == "3"
    assert float(rows["series"]["drift_x_nm"]) == pytest.approx(3 * STEP_PX[0] * PIXEL_NM, abs=0.05)
    assert float(rows["series"]["drift_y_nm"]) == pytest.approx(3 * STEP_PX[1] * PIXEL_NM, abs=0.05)
    # no timing in the files: frames back to back in name order, as import takes them
    assert [doc["cur_frame"] for doc in _track(out / "series" / "track.jsonl")] == [1, 2, 3]

    # the same series named by a glob is the same one recording
    done = run_afmdrift("batch", "series/img_*.npy", "--out", "glob", "--workers", "1",
                        "--pixel-size-nm", str(PIXEL_NM), cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr
    rows = _summary(tmp_path / "glob")
    assert set(rows) == {"series/img_*.npy"}
    assert rows["series/img_*.npy"]["frames"] == "4"
    assert (tmp_path / "glob" / "img" / "track.jsonl").is_file()


@pytest.mark.realdata
def test_a_folder_of_a_nanoscope_series_is_one_recording_as_import_makes_it(
    real_file: Callable[[str], Path], tmp_path: Path
) -> None:
    """Regression: a folder of ``nanoscope3a_15um.002`` and ``.004`` failed with
    "neither a session directory nor a folder of images"."""
    folder = tmp_path / "ns"
    folder.mkdir()
    for name in ("nanoscope3a_15um.004", "nanoscope3a_15um.002"):
        shutil.copy(real_file(name), folder / name)
    done = run_afmdrift("batch", "ns", "--out", "out", "--workers", "1", cwd=tmp_path)
    # the pair is a lattice the content cannot decide: one recording, refused
    assert done.returncode == 1, done.stderr
    rows = _summary(tmp_path / "out")
    assert set(rows) == {"ns"}
    assert rows["ns"]["status"] == "no_drift"
    assert rows["ns"]["frames"] == "2"
    (line,) = _track(tmp_path / "out" / "ns" / "track.jsonl")
    # import's timing: header dates put .002 first, its capture 639 s before .004's
    assert line["ref_t_s"] == 0.0
    assert line["cur_t_s"] == pytest.approx(639.0)
    # with the expected drift given, the prior decides, and the row says so
    done = run_afmdrift("batch", "ns", "--out", "given", "--workers", "1", "--prior-px", "0",
                        "28", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr
    row = _summary(tmp_path / "given")["ns"]
    assert (row["status"], row["valid_frames"], row["prior_decided"]) == ("done", "1", "1")
    assert float(row["drift_y_nm"]) == pytest.approx(28.26 * 15000 / 256, abs=60.0)
