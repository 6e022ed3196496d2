"""Session format v1: round trip, and clear errors for malformed directories."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from afmdrift.drivers import Event, EventKind, ScanDirection
from afmdrift.session import Session, SessionError, SessionMeta, read_session, write_session


def _session(n: int = 3) -> Session:
    rng = np.random.default_rng(0)
    return Session(
        meta=SessionMeta(
            pixel_size_nm=(2.0, 2.5),
            line_time_s=0.25,
            start_time="2026-11-22T10:00:00+00:00",
            source="unit test",
        ),
        frames=rng.normal(size=(n, 16, 24)).astype(np.float32),
        frame_times=np.array([[4.0 * i, 4.0 * i + 4.0] for i in range(n)]),
        directions=[ScanDirection.UP if i % 2 == 0 else ScanDirection.DOWN for i in range(n)],
        channel_t_s=np.array([0.0, 1.0, 2.0]),
        channels={
            "temperature_c": np.array([22.0, 22.5, 23.0]),
            "humidity_pct": np.array([40.0, 41.0, 42.0]),
        },
        events=[Event(1.5, EventKind.OFFSET_MOVE, 10.0, -5.0), Event(3.0, EventKind.TIP_CHANGE)],
        truth=np.array([[0.0, 0.0, 0.0], [10.0, 1.0, -2.0]]),
    )


def test_round_trip(tmp_path: Path) -> None:
    s = _session()
    write_session(s, tmp_path / "s")
    r = read_session(tmp_path / "s")
    np.testing.assert_array_equal(r.frames, s.frames)
    np.testing.assert_array_equal(r.frame_times, s.frame_times)
    assert r.directions == s.directions
    assert r.meta.pixel_size_nm == (2.0, 2.5)
    assert r.events == s.events
    np.testing.assert_allclose(r.channel_at("temperature_c", 0.5), 22.25)
    np.testing.assert_allclose(r.truth_at(5.0), [0.5, -1.0])
    f = r.frame(1)
    assert f.direction is ScanDirection.DOWN
    assert f.t_mid_s == pytest.approx(6.0)
    # a down frame's row 0 is scanned last
    assert f.row_times_s()[0] > f.row_times_s()[-1]


def test_extra_keys_and_columns_are_accepted(tmp_path: Path) -> None:
    write_session(_session(), tmp_path / "s")
    meta = json.loads((tmp_path / "s" / "session.json").read_text())
    meta["instrument"] = "Dimension 3100"
    (tmp_path / "s" / "session.json").write_text(json.dumps(meta))
    r = read_session(tmp_path / "s")
    assert r.meta.extra["instrument"] == "Dimension 3100"


def test_missing_frames_csv_names_the_file(tmp_path: Path) -> None:
    write_session(_session(), tmp_path / "s")
    (tmp_path / "s" / "frames.csv").unlink()
    with pytest.raises(SessionError, match=r"frames\.csv: missing"):
        read_session(tmp_path / "s")


def test_bad_direction_names_file_and_line(tmp_path: Path) -> None:
    write_session(_session(), tmp_path / "s")
    p = tmp_path / "s" / "frames.csv"
    p.write_text(p.read_text().replace(",down", ",sideways"))
    with pytest.raises(SessionError, match=r"frames\.csv:3: direction must be 'up' or 'down'"):
        read_session(tmp_path / "s")


def test_frame_count_mismatch(tmp_path: Path) -> None:
    write_session(_session(), tmp_path / "s")
    np.save(tmp_path / "s" / "frames.npy", np.zeros((2, 16, 24), dtype=np.float32))
    with pytest.raises(SessionError, match="3 rows for 2 frames"):
        read_session(tmp_path / "s")


def test_unknown_event_kind_is_kept_through_a_round_trip(tmp_path: Path) -> None:
    """Regression: a lab's own event kind (door_open) made the whole session unreadable."""
    write_session(_session(), tmp_path / "s")
    p = tmp_path / "s" / "events.csv"
    p.write_text(p.read_text().replace("tip_change", "door_open"))
    s = read_session(tmp_path / "s")
    kinds = [e.kind for e in s.events]
    assert "door_open" in kinds
    assert EventKind.OFFSET_MOVE in kinds
    assert not isinstance(kinds[kinds.index("door_open")], EventKind)
    write_session(s, tmp_path / "s2")
    assert [e.kind for e in read_session(tmp_path / "s2").events] == kinds


@pytest.mark.parametrize("bad", ["Door Open", "2nd_door", "door,open", "x" * 65])
def test_malformed_event_kind_is_rejected(tmp_path: Path, bad: str) -> None:
    write_session(_session(), tmp_path / "s")
    p = tmp_path / "s" / "events.csv"
    text = p.read_text().replace("tip_change", f'"{bad}"' if "," in bad else bad)
    p.write_text(text)
    with pytest.raises(SessionError, match=r"events\.csv:\d+: event kind"):
        read_session(tmp_path / "s")


def test_wrong_format_version(tmp_path: Path) -> None:
    write_session(_session(), tmp_path / "s")
    p = tmp_path / "s" / "session.json"
    p.write_text(p.read_text().replace('"version": 1', '"version": 7'))
    with pytest.raises(SessionError, match="unsupported version 7"):
        read_session(tmp_path / "s")


def test_truncated_npy(tmp_path: Path) -> None:
    write_session(_session(), tmp_path / "s")
    p = tmp_path / "s" / "frames.npy"
    p.write_bytes(p.read_bytes()[:100])
    with pytest.raises(SessionError, match=r"frames\.npy"):
        read_session(tmp_path / "s")
