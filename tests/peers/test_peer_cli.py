"""Peer battery through the command line: ``afmdrift measure --json``.

A few pair cases of ``_battery.py`` (large shifts with little overlap, one
feature on a flat frame, a 129² frame, the line grid, gold-like particles
with a quarter changed, the real NanoScope frame) are written as ``.npy``
files and measured by the CLI, which must never print a valid result more
than max(0.5 px, 4σ) from the truth, and must give a reason when it refuses
(exit 1: invalid result; exit 2: the input was refused).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _battery import CASES_BY_ID, MissingDataError, Pair, describe, judge_pair

from afmdrift.cli import main

CLI_CASES = [
    "skimage:disambiguate_+350_+350",
    "opencv:rectangle_128x129",
    "opencv:real_image_129",
    "suite2p:line_grid_01_-7_+3",
    "issue13:gold_quarter_changed",
    "issue13:nanoscope_fourier_7.6_7.0",
]


@pytest.mark.parametrize(
    "case_id",
    [
        pytest.param(c, id=c, marks=[pytest.mark.realdata] if CASES_BY_ID[c].realdata else [])
        for c in CLI_CASES
    ],
)
def test_cli_gives_no_confident_wrong_answer(
    case_id: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    case = CASES_BY_ID[case_id]
    try:
        pair = case.build()
    except MissingDataError as err:
        pytest.skip(str(err))
    assert isinstance(pair, Pair)
    ref, cur = tmp_path / "ref.npy", tmp_path / "cur.npy"
    np.save(ref, pair.reference)
    np.save(cur, pair.current)
    capsys.readouterr()
    code = main(
        ["measure", str(ref), str(cur), "--pixel-size-nm", repr(pair.pixel_size_nm), "--json"]
    )
    out, err = capsys.readouterr()
    if code == 2:
        assert err.strip(), "input refused without a message"
        return
    r = json.loads(out)
    assert code == (0 if r["valid"] else 1)
    o = judge_pair(
        case,
        pair,
        valid=bool(r["valid"]),
        got=(float(r["dx_px"] or np.nan), float(r["dy_px"] or np.nan)),
        sigma_nm=(float(r["sigma_x_nm"] or np.nan), float(r["sigma_y_nm"] or np.nan)),
        reason=r["reason"],
    )
    assert o.verdict != "fail", "CLI: confident wrong answer: " + describe(o)
    if o.verdict == "refused":
        assert o.reason, describe(o)
