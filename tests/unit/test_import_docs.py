"""``docs/session-format.md`` stays true to the reader."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from afmdrift.session import read_session

DOC = Path(__file__).resolve().parents[2] / "docs" / "session-format.md"


def test_python_example_writes_a_readable_session(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)
    assert len(blocks) == 1
    monkeypatch.chdir(tmp_path)
    exec(compile(blocks[0], str(DOC), "exec"), {})
    s = read_session(tmp_path / "my-session")
    assert np.asarray(s.frames).shape == (3, 512, 512)
    assert [d.value for d in s.directions] == ["up", "down", "up"]
    np.testing.assert_allclose(s.frame_times[2], [512.0, 640.0])
    assert s.meta.pixel_size_nm == (9.77, 9.77)


def test_example_json_and_csv_blocks_parse(tmp_path: Path) -> None:
    text = DOC.read_text(encoding="utf-8")
    json_block = re.search(r"`session.json`\n```json\n(.*?)```", text, re.S)
    csv_block = re.search(r"`frames.csv`\n```\n(.*?)```", text, re.S)
    assert json_block is not None
    assert csv_block is not None
    root = tmp_path / "ns"
    root.mkdir()
    (root / "session.json").write_text(json_block.group(1), encoding="utf-8")
    (root / "frames.csv").write_text(csv_block.group(1), encoding="utf-8")
    np.save(root / "frames.npy", np.zeros((2, 256, 256)))
    s = read_session(root)
    assert s.meta.extra["channel"] == "Height"
    assert s.meta.line_time_s == pytest.approx(1 / 1.50498)
    np.testing.assert_allclose(s.frame_times[1], [639.0, 809.1019282648274])


def test_big_endian_frames_are_accepted(tmp_path: Path) -> None:
    """Regression: a big-endian float64 frames.npy (LabVIEW's default byte order)
    is a valid session; the reader rejected it as 'not float32 or float64'."""
    root = tmp_path / "be"
    root.mkdir()
    frames = np.arange(2 * 4 * 5, dtype=">f8").reshape(2, 4, 5)
    np.save(root / "frames.npy", frames)
    (root / "session.json").write_text(
        '{"format": "afmdrift-session", "version": 1, "pixel_size_nm": 2.0, "line_time_s": 0.1}'
    )
    (root / "frames.csv").write_text("frame,t_start_s,t_end_s,direction\n0,0,1,up\n1,1,2,DOWN\n")
    s = read_session(root)
    np.testing.assert_array_equal(np.asarray(s.frames), frames)
    assert s.meta.pixel_size_nm == (2.0, 2.0)
    assert [d.value for d in s.directions] == ["up", "down"]
