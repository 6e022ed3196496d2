"""``import_files`` and ``afmdrift import`` on files written here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from afmdrift.cli import main
from afmdrift.io import ImageFileError
from afmdrift.session import SessionError, import_files, read_session


def _write_nc(path: Path, stack: np.ndarray, *, start: str, line_time_s: float | None) -> None:
    from scipy.io import netcdf_file

    with netcdf_file(path, "w") as nc:
        nc.start_time = start
        if line_time_s is not None:
            nc.line_time_s = line_time_s
        nc.scan_direction = "down"
        nc.createDimension("frame", stack.shape[0])
        nc.createDimension("y", stack.shape[1])
        nc.createDimension("x", stack.shape[2])
        t = nc.createVariable("time", "f8", ("frame",))
        t[:] = np.arange(stack.shape[0]) * 4.0
        t.units = "s"
        h = nc.createVariable("Height", "f8", ("frame", "y", "x"))
        h[:] = stack
        h.units = "nm"


def _stack(n: int, rows: int = 16, cols: int = 20, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, rows, cols))


def test_files_are_sorted_by_timestamp_and_timed_from_headers(tmp_path: Path) -> None:
    late, early = tmp_path / "late.nc", tmp_path / "early.nc"
    _write_nc(late, _stack(2, seed=1), start="2024-01-01T10:01:00", line_time_s=0.1)
    _write_nc(early, _stack(2, seed=2), start="2024-01-01T10:00:00", line_time_s=0.1)
    s = import_files([late, early], pixel_size_nm=(2.0, 3.0))
    np.testing.assert_allclose(s.frame_times[:, 0], [0.0, 4.0, 60.0, 64.0])
    np.testing.assert_allclose(s.frame_times[:, 1] - s.frame_times[:, 0], 1.6)  # 16 rows x 0.1 s
    np.testing.assert_array_equal(s.frames[0], _stack(2, seed=2)[0])
    np.testing.assert_array_equal(s.frames[3], _stack(2, seed=1)[1])
    assert [d.value for d in s.directions] == ["down"] * 4
    assert s.meta.line_time_s == pytest.approx(0.1)
    assert s.meta.pixel_size_nm == (2.0, 3.0)
    assert s.meta.start_time == "2024-01-01T10:00:00"
    assert s.meta.extra["frame_sources"][0] == f"{early}:0"


def test_frame_interval_gives_timing_when_header_has_no_line_time(tmp_path: Path) -> None:
    p = tmp_path / "a.nc"
    _write_nc(p, _stack(3), start="2024-01-01T10:00:00", line_time_s=None)
    s = import_files([p], pixel_size_nm=1.0)
    np.testing.assert_allclose(s.frame_times, [[0, 4], [4, 8], [8, 12]])
    assert s.meta.line_time_s == pytest.approx(4.0 / 16)
    assert "median frame interval 4 s" in s.meta.source
    assert "frame time / rows" in s.meta.source


def test_untimed_files_need_frame_time(tmp_path: Path) -> None:
    p = tmp_path / "a.npy"
    np.save(p, _stack(3))
    with pytest.raises(SessionError, match=r"a\.npy:0: the file gives no frame timing"):
        import_files([p], pixel_size_nm=1.0)
    s = import_files([p], pixel_size_nm=1.0, frame_time_s=2.0)
    np.testing.assert_allclose(s.frame_times, [[0, 2], [2, 4], [4, 6]])
    assert [d.value for d in s.directions] == ["up"] * 3
    assert "'up' assumed" in s.meta.source
    assert s.meta.start_time == ""


def test_inconsistent_shapes_and_pixel_sizes_name_the_file(tmp_path: Path) -> None:
    a, b = tmp_path / "a.npy", tmp_path / "b.npy"
    np.save(a, _stack(1)[0])
    np.save(b, _stack(1, rows=8)[0])
    with pytest.raises(SessionError, match=r"b\.npy: image is 8x20 px but .*a\.npy is 16x20"):
        import_files([a, b], pixel_size_nm=1.0, frame_time_s=1.0)
    c, d = tmp_path / "c.nc", tmp_path / "d.nc"
    _write_nc(c, _stack(1), start="2024-01-01T10:00:00", line_time_s=0.1)
    _write_nc(d, _stack(1), start="2024-01-01T10:00:09", line_time_s=0.1)
    # Give the two files different calibrations through x/y coordinate variables.
    for path, step in ((c, 1e-9), (d, 2e-9)):
        from scipy.io import netcdf_file

        with netcdf_file(path, "a") as nc:
            for dim, n in (("x", 20), ("y", 16)):
                v = nc.createVariable(dim, "f8", (dim,))
                v[:] = np.arange(n) * step
                v.units = "m"
    with pytest.raises(SessionError, match=r"d\.nc:0: pixel size \(2\.0, 2\.0\) nm differs"):
        import_files([c, d])


def test_mixed_timestamps_are_rejected(tmp_path: Path) -> None:
    a, b = tmp_path / "a.nc", tmp_path / "b.npy"
    _write_nc(a, _stack(1), start="2024-01-01T10:00:00", line_time_s=0.1)
    np.save(b, _stack(1)[0])
    with pytest.raises(SessionError, match=r"b\.npy: no timestamp"):
        import_files([a, b], pixel_size_nm=1.0)


def test_no_files_and_unreadable_file(tmp_path: Path) -> None:
    with pytest.raises(SessionError, match="no input files"):
        import_files([])
    with pytest.raises(ImageFileError, match=r"gone\.spm: no such file"):
        import_files([tmp_path / "gone.spm"])


def test_cli_import_writes_a_readable_session(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "m.nc"
    _write_nc(src, _stack(3), start="2024-01-01T10:00:00", line_time_s=0.05)
    out = tmp_path / "session"
    assert main(["import", str(src), "--out", str(out), "--pixel-size-nm", "2", "3"]) == 0
    assert "3 frame(s) of 16x20 px" in capsys.readouterr().out
    s = read_session(out)
    assert len(s) == 3
    assert s.meta.pixel_size_nm == (2.0, 3.0)
    np.testing.assert_allclose(s.frame_times[:, 0], [0, 4, 8])
    np.testing.assert_array_equal(np.asarray(s.frames), _stack(3))
    assert json.loads((out / "session.json").read_text())["channel"] == "Height"
    # A second import into the same, now non-empty, directory is refused without --force.
    assert main(["import", str(src), "--out", str(out)]) == 2
    assert "not an empty directory" in capsys.readouterr().err
    assert main(["import", str(src), "--out", str(out), "--force", "--pixel-size-nm", "2"]) == 0


def test_cli_import_error_has_no_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    p = tmp_path / "a.npy"
    np.save(p, _stack(1)[0])
    assert main(["import", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "a.npy" in err
    assert "pixel_size_nm" in err
    assert "Traceback" not in err


def test_cli_import_attaches_a_lab_event_log_with_its_own_kinds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Regression guard: a lab's event log (door_open, stage_move) and an extra
    channel (pressure_hpa) reach the session; unknown kinds used to be rejected."""
    src = tmp_path / "m.nc"
    _write_nc(src, _stack(3), start="2024-01-01T10:00:00", line_time_s=0.05)
    ev = tmp_path / "lab-events.csv"
    ev.write_text("t_s,kind,x_nm,y_nm\n5.5,door_open,,\n2.0,stage_move,10,0\n")
    ch = tmp_path / "lab-channels.csv"
    ch.write_text("t_s,pressure_hpa\n0,1013.2\n6,1013.0\n12,1012.9\n")
    out = tmp_path / "session"
    args = ["import", str(src), "--out", str(out), "--pixel-size-nm", "2"]
    assert main([*args, "--events", str(ev), "--channels", str(ch)]) == 0
    s = read_session(out)
    assert [(e.t_s, str(e.kind), e.x_nm) for e in s.events] == [
        (2.0, "stage_move", 10.0),
        (5.5, "door_open", 0.0),
    ]
    np.testing.assert_allclose(s.channels["pressure_hpa"], [1013.2, 1013.0, 1012.9])
    capsys.readouterr()
    assert main([*args, "--force", "--events", str(tmp_path / "missing.csv")]) == 2
    assert "missing.csv: event log not found" in capsys.readouterr().err


def test_a_stack_file_is_held_once(tmp_path: Path) -> None:
    """``afmdrift measure STACK.npy``: the reader's frames are views of one
    float64 stack, and the session keeps that stack instead of copying it
    (a copy of a long stack cost half a second and doubled the memory)."""
    from afmdrift.io import load_stack
    from afmdrift.session import session_from_images

    rng = np.random.default_rng(0)
    stack = rng.standard_normal((5, 64, 80)).astype(np.float32)
    path = tmp_path / "stack.npy"
    np.save(path, stack)
    images = load_stack(path, pixel_size_nm=2.0)
    session = session_from_images(images, frame_time_s=1.0)
    np.testing.assert_array_equal(session.frames, stack.astype(np.float64))
    assert session.frames.dtype == np.float64
    assert all(np.shares_memory(session.frames, im.heights_nm) for im in images)
    # heights in µm are scaled once, into the stack the frames share
    scaled = load_stack(path, pixel_size_nm=2.0, height_unit="um")
    np.testing.assert_allclose(scaled[3].heights_nm, 1e3 * stack[3].astype(np.float64))
    # frames given in another order (or from separate files) are copied, in
    # the order given
    reordered = session_from_images(images[::-1], frame_time_s=1.0)
    assert not np.shares_memory(reordered.frames, images[0].heights_nm)
    np.testing.assert_array_equal(reordered.frames, stack[::-1].astype(np.float64))


def test_one_frame_of_a_stack_file_does_not_keep_the_stack(tmp_path: Path) -> None:
    """``FILE:i`` gives the frame its own heights (a view would hold the
    whole float64 stack for as long as the frame lives); a Fortran-ordered
    ``.npy`` is read into one C-ordered stack whose frames the session
    shares (not copied once more to make it contiguous)."""
    from afmdrift.io import load_image, load_stack
    from afmdrift.session import session_from_images

    stack = np.random.default_rng(1).standard_normal((4, 48, 40))
    path = tmp_path / "stack.npy"
    np.save(path, np.asfortranarray(stack))
    one = load_image(f"{path}:2", pixel_size_nm=1.0)
    np.testing.assert_array_equal(one.heights_nm, stack[2])
    assert one.heights_nm.base is None
    images = load_stack(path, pixel_size_nm=1.0)
    assert all(im.heights_nm.flags.c_contiguous for im in images)
    session = session_from_images(images, frame_time_s=1.0)
    np.testing.assert_array_equal(session.frames, stack)
    assert np.shares_memory(session.frames, images[3].heights_nm)
