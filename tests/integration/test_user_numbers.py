"""No number silently wrong on a user's own files (issue 37), through the CLI.

Each test runs the command a new user runs, on a session, stack or file pair
of the kind the issue names, and fails on the code before the fix: a track
that ignored its session's offset moves, a refusal written as drift 0.0, a
shift the prior alone picked reported as any other, a pixel size option that
overrode a calibrated header in one command and not in another.
"""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from afmdrift.cli import main
from afmdrift.io import write_tif
from afmdrift.testing import generate_track, lattice_texture, shifted_crop

REPO = Path(__file__).resolve().parents[2]
PRESSURE = REPO / "config" / "scenarios" / "hidden" / "pressure.toml"


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "afmdrift", *args],
        cwd=cwd, capture_output=True, text=True, timeout=240,
    )  # fmt: skip


def _summary(out: Path) -> list[dict[str, str]]:
    with (out / "summary.csv").open(encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _measurements(run: Path) -> dict[int, tuple[float, float]]:
    with (run / "measurements.csv").open(encoding="utf-8") as fh:
        return {
            int(r["frame"]): (float(r["image_x_nm"]), float(r["image_y_nm"]))
            for r in csv.DictReader(fh)
            if r["valid"] == "1" and r["image_x_nm"]
        }


@pytest.mark.slow
def test_batch_track_of_a_session_takes_its_offset_moves_as_replay_does(tmp_path: Path) -> None:
    """Regression (issue 37, item 1): ``batch`` on the tutorial's pressure session
    at seed 5 put frame 65, after a commanded move of (-120, +130) nm, at
    (-16.4, +14.6) px where the image moved (+16, -17.6) px, and stayed
    300-400 nm off; the track ignored the event log that ``replay`` uses."""
    rec = _cli("sim", "record", str(PRESSURE), "--out", "s", "--seed", "5", "--frames", "72",
               cwd=tmp_path)  # fmt: skip
    assert rec.returncode == 0, rec.stderr
    batch = _cli("batch", "s", "--out", "r", "--workers", "1", cwd=tmp_path)
    assert batch.returncode == 0, batch.stderr
    replay = _cli("replay", "s", "--out", "run", cwd=tmp_path)
    assert replay.returncode == 0, replay.stderr
    want = _measurements(tmp_path / "run")
    lines = (tmp_path / "r" / "s" / "track.jsonl").read_text(encoding="utf-8").splitlines()
    track = [json.loads(line) for line in lines]
    assert len(track) == 71
    compared = 0
    for doc in track:
        if doc["valid"] and doc["cur_frame"] in want:
            x, y = want[doc["cur_frame"]]
            assert abs(doc["cumulative_dx_nm"] - x) < 1.0, doc["cur_frame"]
            assert abs(doc["cumulative_dy_nm"] - y) < 1.0, doc["cur_frame"]
            compared += 1
    assert compared >= 65
    row = _summary(tmp_path / "r")[0]
    assert row["status"] == "done"
    last = max(want)
    assert abs(float(row["drift_x_nm"]) - want[last][0]) < 1.0
    assert abs(float(row["drift_y_nm"]) - want[last][1]) < 1.0


def test_measure_stack_without_event_log_is_not_confidently_wrong_after_an_unlogged_jump(
    tmp_path: Path,
) -> None:
    """Regression (issue 37, item 1, the class): 128-px frames whose 64/128
    blocks overlap heavily agreed (15 of 16) on a false peak when the content
    jumped 28 px with no event log to say so; the whole-frame alignment now
    checks a result that lands far from the prediction."""
    g = generate_track(size_px=128, seed=2, frames=30, moves=True, sample="rough")
    np.save(tmp_path / "stack.npy", g.frames)
    px = g.pixel_size_nm[0]
    out = _cli("measure", "stack.npy", "--pixel-size-nm", str(px), cwd=tmp_path)
    assert out.returncode in (0, 1), out.stderr
    prev_k, prev = 0, np.zeros(2)
    accepted = 0
    for line in out.stdout.splitlines():
        doc = json.loads(line)
        if not doc["valid"]:
            continue
        k = doc["cur_frame"]
        m = np.array([doc["cumulative_dx_px"], doc["cumulative_dy_px"]])
        want = g.image_px[k] - g.image_px[prev_k]
        sig = np.array([doc["sigma_x_nm"], doc["sigma_y_nm"]]) / px
        assert np.all(np.abs((m - prev) - want) <= np.maximum(1.0, 3 * sig)), k
        prev_k, prev = k, m
        accepted += 1
    assert accepted >= 24


def _lattice_pair(tmp_path: Path, shift: tuple[float, float]) -> tuple[str, str]:
    tex = lattice_texture((320, 320), rng=np.random.default_rng(3))
    ref = shifted_crop(tex, shape=(192, 192))
    cur = shifted_crop(tex, shape=(192, 192), dx_px=shift[0], dy_px=shift[1])
    np.save(tmp_path / "ref.npy", ref)
    np.save(tmp_path / "cur.npy", cur)
    return str(tmp_path / "ref.npy"), str(tmp_path / "cur.npy")


def test_refused_measurement_is_a_no_drift_row_not_zero(tmp_path: Path) -> None:
    """Regression (issue 37, item 2): a recording whose only measurement was
    refused as ambiguous read ``done,2,1,0.0,0.0`` in summary.csv."""
    ref, cur = _lattice_pair(tmp_path, (3.4, -1.2))
    np.save(tmp_path / "pair.npy", np.stack([np.load(ref), np.load(cur)]))
    out = _cli("batch", "pair.npy", "--out", "r", "--pixel-size-nm", "1", "--workers", "1",
               cwd=tmp_path)  # fmt: skip
    assert out.returncode == 1, out.stderr
    row = _summary(tmp_path / "r")[0]
    assert row["status"] == "no_drift"
    assert row["drift_x_nm"] == ""
    assert row["drift_y_nm"] == ""
    assert row["valid_frames"] == "0"
    assert "ambiguous" in row["error"]
    assert "no drift: pair.npy" in out.stderr


@pytest.mark.realdata
def test_refused_nanoscope_pair_is_no_drift(tmp_path: Path, real_file) -> None:  # type: ignore[no-untyped-def]
    """Regression (issue 37, item 2), the README's own NanoScope pair."""
    a, b = real_file("nanoscope3a_15um.002"), real_file("nanoscope3a_15um.004")
    assert _cli("import", str(a), str(b), "--out", "ns", cwd=tmp_path).returncode == 0
    out = _cli("batch", "ns", "--out", "r", "--workers", "1", cwd=tmp_path)
    row = _summary(tmp_path / "r")[0]
    assert (row["status"], row["frames"], row["valid_frames"]) == ("no_drift", "2", "0")
    assert row["drift_x_nm"] == ""
    assert out.returncode == 1
    doc = json.loads((tmp_path / "r" / "ns" / "track.jsonl").read_text())
    assert doc["valid"] is False
    assert doc["dx_nm"] is None


def test_prior_decided_lattice_shift_says_so_and_exits_3(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Regression (issue 37, item 3): ``--prior-px 0 0`` on a lattice gave
    ``valid: true`` with exit 0 and nothing said that the prior alone picked
    the shift; the printed prior was the search centre, not the one given."""
    ref, cur = _lattice_pair(tmp_path, (3.4, -1.2))
    code = main(["measure", ref, cur, "--pixel-size-nm", "1", "--prior-px", "0", "0", "--json"])
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert code == 3
    assert doc["valid"] is True
    assert doc["decided_by"] == "prior"
    assert doc["given_prior_px"] == [0.0, 0.0]
    assert doc["expected_px"] == [0.0, 0.0]
    assert doc["alternatives"]
    assert doc["ambiguity_px"] > 5.0
    nearest = min(a["from_prior_px"] for a in doc["alternatives"])
    assert nearest >= math.hypot(doc["dx_px"], doc["dy_px"]) - 0.5
    assert "the prior alone picked this shift" in captured.err
    # the refusal names the command-line option
    assert main(["measure", ref, cur, "--pixel-size-nm", "1", "--json"]) == 1
    refused = json.loads(capsys.readouterr().out)
    assert "--prior-px" in refused["reason"]
    # the text output prints the prior given
    assert main(["measure", ref, cur, "--pixel-size-nm", "1", "--prior-px", "0", "0"]) == 3
    text = capsys.readouterr().out
    assert "prior      +0, +0 px given" in text
    assert "DECIDED BY THE PRIOR" in text


def test_prior_of_a_stack_decides_its_first_increment(tmp_path: Path) -> None:
    """Regression (issue 37, item 3): ``--prior-px`` was refused for a stack,
    and a lattice stack's first pair could only be refused."""
    ref, cur = _lattice_pair(tmp_path, (3.4, -1.2))
    np.save(tmp_path / "pair.npy", np.stack([np.load(ref), np.load(cur)]))
    plain = _cli("measure", "pair.npy", "--pixel-size-nm", "1", cwd=tmp_path)
    assert plain.returncode == 1
    given = _cli("measure", "pair.npy", "--pixel-size-nm", "1", "--prior-px", "3", "-1",
                 cwd=tmp_path)  # fmt: skip
    assert given.returncode == 3, given.stderr
    doc = json.loads(given.stdout)
    assert doc["decided_by"] == "prior"
    assert abs(doc["dx_px"] - 3.4) < 0.3
    assert abs(doc["dy_px"] + 1.2) < 0.3


def test_pixel_size_serves_files_without_calibration_and_override_prints_both(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Regression (issue 37, item 4): ``measure --pixel-size-nm`` silently
    replaced a calibrated header (58.59 -> 10 nm) where ``batch`` kept it."""
    rng = np.random.default_rng(5)
    base = 3.0 * rng.normal(size=(192, 192))
    base = np.real(np.fft.ifft2(np.fft.fft2(base) * np.exp(-0.02 * np.add.outer(
        np.fft.fftfreq(192) ** 2, np.fft.fftfreq(192) ** 2) * 192 ** 2)))  # fmt: skip
    write_tif(tmp_path / "a.tif", base, pixel_size_nm=(5.0, 5.0))
    write_tif(tmp_path / "b.tif", np.roll(base, 4, axis=0), pixel_size_nm=(5.0, 5.0))
    a, b = str(tmp_path / "a.tif"), str(tmp_path / "b.tif")
    assert main(["measure", a, b, "--pixel-size-nm", "10", "--json"]) == 0
    out = capsys.readouterr()
    doc = json.loads(out.out)
    assert doc["pixel_size_nm"] == [5.0, 5.0]
    assert abs(doc["dy_nm"] - 20.0) < 0.5
    assert "5 x 5 nm is kept" in out.err
    assert "10 x 10 nm" in out.err
    assert main(["measure", a, b, "--pixel-size-nm", "10", "--override-pixel-size", "--json"]) == 0
    out = capsys.readouterr()
    doc = json.loads(out.out)
    assert doc["pixel_size_nm"] == [10.0, 10.0]
    assert abs(doc["dy_nm"] - 40.0) < 1.0
    assert "replaces the header's 5 x 5 nm" in out.err
    assert main(["measure", a, b, "--override-pixel-size"]) == 2
    assert "--override-pixel-size needs --pixel-size-nm" in capsys.readouterr().err
