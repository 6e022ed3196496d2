"""``afmdrift diagnose`` on two real STM atom-tracking records (``openspm/``).

The records of ``../shared/data/real/openspm`` (see its README) are drift
logs of one point a minute with no channel, whose only events are the
controller's half-hourly file boundaries (``tracking_setting``). In
``openspm-0368`` (6.5 h) the position jumps by about 215 nm over two points
near t = 19 200 s, where a boundary is logged as at the 12 others that show
no jump: the event kind does not explain it, a jump at that time does. Read
in place; never copied into the repository.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from afmdrift.config import AfmdriftConfig
from afmdrift.diagnostics import DiagnoseOptions, diagnose_path, diagnosis_text

pytestmark = pytest.mark.realdata


def _record(real_data_dir: Path, name: str) -> Path:
    path = real_data_dir / "openspm" / name
    if not (path / "positions.csv").is_file():
        pytest.skip(f"real drift record {name} not found in {real_data_dir / 'openspm'}")
    return path


def test_the_jump_of_openspm_0368_is_discovered_beside_the_logged_boundary(
    real_data_dir: Path,
) -> None:
    """The jump is found at its time with its search paid for (in-sample
    evidence over every frame boundary), next to the logged boundary whose
    kind's own term explains nothing, and the plain paragraph names it with
    the term to add; whether adding it helps the predictions is measured,
    not assumed (after this jump the drift follows another course)."""
    dg, _ = diagnose_path(
        _record(real_data_dir, "openspm-0368"),
        config=AfmdriftConfig(),
        options=DiagnoseOptions(),
    )
    j = dg.to_json()
    jumps = [c for c in j["candidates"] if (c["discovered"] or {}).get("kind") == "jump"]
    assert jumps[0]["in_sample_ok"]
    assert 19000.0 <= jumps[0]["discovered"]["t_s"] <= 19400.0
    # The step between the frames either side of t_s; the position moves over two frames.
    step_x, step_y = jumps[0]["discovered"]["step_nm"]
    assert step_x < -80.0
    assert step_y > 100.0
    event = next(c for c in j["candidates"] if c["effect"] == "event:tracking_setting")
    assert not event["significant"]
    first = diagnosis_text(j).splitlines()[0]
    assert "a jump of (\u2212" in first
    assert f"`{jumps[0]['term']}`" in first


def test_openspm_1024_claims_nothing_it_cannot_show(real_data_dir: Path) -> None:
    """The slow, quiet record: no discovered shape is significant."""
    dg, _ = diagnose_path(
        _record(real_data_dir, "openspm-1024"),
        config=AfmdriftConfig(),
        options=DiagnoseOptions(),
    )
    j = dg.to_json()
    assert not any(c["significant"] and c["discovered"] for c in j["candidates"])
