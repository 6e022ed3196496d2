"""Corrupt, hostile or oversized files: image files, session directories and
configuration files give one typed error naming the file, never a traceback,
a hang or a multi-TiB allocation (issue "A daemon that cannot be knocked over").

Named regression tests first, then Hypothesis fuzzing of each reader.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from service_sim import small_scenario

from afmdrift.config import load_config
from afmdrift.drivers.sim._record import record_session
from afmdrift.errors import ConfigError, InputError
from afmdrift.io import load_stack
from afmdrift.io._image import ImageFileError
from afmdrift.session import read_session

FUZZ = settings(
    max_examples=120,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("session") / "s"
    record_session(small_scenario(), root, frames=4)
    return root


def _copy(session_dir: Path, tmp_path: Path) -> Path:
    out = tmp_path / "copy"
    shutil.copytree(session_dir, out)
    return out


def _run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "afmdrift", *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


# ---------------------------------------------------------------------- images


def test_npy_declaring_terabytes_is_refused_before_allocating(tmp_path: Path) -> None:
    """Regression: a .npy header of 10^12 values made measure try to allocate 3.6 TiB."""
    header = "{'descr': '<f4', 'fortran_order': False, 'shape': (1000000, 1000000), }"
    header = header.ljust(118) + "\n"
    path = tmp_path / "huge.npy"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode())
    with pytest.raises(ImageFileError, match=r"huge\.npy: not a readable \.npy array"):
        load_stack(path, pixel_size_nm=1.0)


def test_npy_over_the_value_limit_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "big.npy"
    np.lib.format.open_memmap(path, mode="w+", dtype=np.uint8, shape=(5, 8192, 8192)).flush()
    with pytest.raises(ImageFileError, match="declares 335544320 values"):
        load_stack(path, pixel_size_nm=1.0)


def test_four_byte_tif_gives_one_line(tmp_path: Path) -> None:
    """Regression: a 4-byte .tif gave a struct.error traceback from the reader."""
    path = tmp_path / "tiny.tif"
    path.write_bytes(b"II*\x00")
    with pytest.raises(ImageFileError, match=r"tiny.tif: not a readable"):
        load_stack(path, pixel_size_nm=1.0)
    done = _run_cli("measure", str(path), str(path), "--pixel-size-nm", "1")
    assert done.returncode == 2
    assert "Traceback" not in done.stderr
    assert done.stderr.strip().startswith("afmdrift: error:")


@pytest.mark.realdata
def test_asd_with_a_zero_header_field_gives_one_line(real_file, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """Regression: an .asd header field set to zero raised ZeroDivisionError
    inside the reader."""
    data = bytearray(real_file("hsafm_sample_0.asd").read_bytes())
    data[48:52] = b"\0\0\0\0"
    path = tmp_path / "zero.asd"
    path.write_bytes(bytes(data))
    with pytest.raises(ImageFileError, match=r"zero\.asd: not a readable \.asd file"):
        load_stack(path)


@FUZZ
@given(
    data=st.binary(max_size=4096),
    suffix=st.sampled_from(
        [".npy", ".tif", ".asd", ".gwy", ".nc", ".spm", ".001", ".ibw", ".jpk", ".h5-jpk", ".stp"]
    ),
)
def test_fuzz_image_readers_raise_only_image_file_errors(
    tmp_path: Path, data: bytes, suffix: str
) -> None:
    path = tmp_path / f"fuzz{suffix}"
    path.write_bytes(data)
    error: ImageFileError | None = None
    try:
        load_stack(path, pixel_size_nm=1.0, height_unit="nm")
    except ImageFileError as err:
        error = err
    assert error is None or str(path) in str(error)


# ---------------------------------------------------------------------- sessions


def test_session_json_nested_deeply_is_refused(session_dir: Path, tmp_path: Path) -> None:
    """Regression: replay of a session.json nested 100 000 deep: RecursionError."""
    s = _copy(session_dir, tmp_path)
    doc = (s / "session.json").read_text()
    (s / "session.json").write_text(
        doc.rstrip()[:-1] + ', "x": ' + "[" * 100_000 + "]" * 100_000 + "}"
    )
    with pytest.raises(InputError, match="nested deeper"):
        read_session(s)


def test_session_pixel_size_of_1e308_is_refused(session_dir: Path, tmp_path: Path) -> None:
    """Regression: pixel_size_nm = 1e308 gave an OverflowError traceback in replay."""
    s = _copy(session_dir, tmp_path)
    doc = json.loads((s / "session.json").read_text())
    doc["pixel_size_nm"] = [1e308, 1e308]
    (s / "session.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="pixel_size_nm must be"):
        read_session(s)
    done = _run_cli("replay", str(s), "--out", str(tmp_path / "run"))
    assert done.returncode == 2
    assert "Traceback" not in done.stderr


def test_binary_frames_csv_is_refused_with_its_line(session_dir: Path, tmp_path: Path) -> None:
    """Regression: a binary frames.csv gave a UnicodeDecodeError traceback."""
    s = _copy(session_dir, tmp_path)
    (s / "frames.csv").write_bytes(b"\x00\xff\xfe\x01" * 1000)
    with pytest.raises(InputError, match=r"frames.csv:\d+: not UTF-8"):
        read_session(s)


def test_csv_field_over_the_csv_limit_is_refused(session_dir: Path, tmp_path: Path) -> None:
    """Regression: a field of over 128 KiB raised csv.Error from the reader."""
    s = _copy(session_dir, tmp_path)
    lines = (s / "frames.csv").read_text().splitlines()
    lines[1] += "," + "x" * 200_000
    (s / "frames.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"frames.csv:\d+: not valid CSV"):
        read_session(s)


def test_frames_csv_with_a_byte_order_mark_is_read(session_dir: Path, tmp_path: Path) -> None:
    """Regression: a frames.csv saved with a UTF-8 BOM (spreadsheets do) was rejected."""
    s = _copy(session_dir, tmp_path)
    (s / "frames.csv").write_bytes(b"\xef\xbb\xbf" + (s / "frames.csv").read_bytes())
    assert len(read_session(s)) == 4


def test_import_force_over_an_old_session_leaves_none_of_its_files(
    session_dir: Path, tmp_path: Path
) -> None:
    """Regression: import --force kept the old session's truth.csv, channels.csv
    and events.csv: the new movie silently carried another session's truth."""
    out = _copy(session_dir, tmp_path)
    assert (out / "truth.csv").is_file()
    stack = np.random.default_rng(1).normal(size=(3, 64, 64)).astype(np.float32)
    np.save(tmp_path / "movie.npy", stack)
    done = _run_cli(
        "import", str(tmp_path / "movie.npy"), "--out", str(out), "--force",
        "--pixel-size-nm", "1", "--frame-time-s", "10",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    for name in (
        "truth.csv",
        "channels.csv",
        "events.csv",
        "truth_components.csv",
        "scenario.json",
    ):
        assert not (out / name).exists(), name
    assert read_session(out).truth is None


_session_files = st.sampled_from(
    ["session.json", "frames.csv", "channels.csv", "events.csv", "truth.csv"]
)


@FUZZ
@given(name=_session_files, data=st.binary(max_size=2048))
def test_fuzz_session_reader_raises_only_input_errors(
    session_dir: Path, tmp_path: Path, name: str, data: bytes
) -> None:
    s = tmp_path / "fuzz"
    if s.exists():
        shutil.rmtree(s)
    shutil.copytree(session_dir, s)
    (s / name).write_bytes(data)
    error: InputError | None = None
    try:
        read_session(s)
    except InputError as err:
        error = err
    assert error is None or name in str(error)


# ---------------------------------------------------------------------- configuration


@pytest.mark.parametrize("kind", ["fifo", "dev_zero", "binary", "deep"])
def test_config_that_is_not_a_config_file(tmp_path: Path, kind: str) -> None:
    """Regression: a FIFO hung, /dev/zero grew without bound, non-UTF-8 and deeply
    nested TOML gave tracebacks."""
    if kind == "fifo":
        path = tmp_path / "fifo.toml"
        os.mkfifo(path)
        match = "not a regular file"
    elif kind == "dev_zero":
        path = Path("/dev/zero")
        match = "not a regular file"
    elif kind == "binary":
        path = tmp_path / "bin.toml"
        path.write_bytes(b"[service]\nrun_dir = '\xff\xfe'\n")
        match = "not UTF-8"
    else:
        path = tmp_path / "deep.toml"
        path.write_text("x = " + "[" * 50_000 + "]" * 50_000 + "\n")
        match = "nested too deeply|not valid TOML"
    with pytest.raises(ConfigError, match=match):
        load_config(path)


@FUZZ
@given(text=st.text(max_size=400))
def test_fuzz_config_loader_raises_only_config_errors(tmp_path: Path, text: str) -> None:
    path = tmp_path / "fuzz.toml"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    with contextlib.suppress(ConfigError):  # any other exception fails the test
        load_config(path)
