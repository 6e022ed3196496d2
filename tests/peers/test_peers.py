"""Peer battery: the translation cases of scikit-image, OpenCV, imreg_dft,
pystackreg, suite2p and afspm, and the issue's own cases, re-created in our
own code (facts only, each source named in ``_battery.py``, which
``benchmarks/peer_battery.py`` runs too and prints as a table per peer).

Two checks per case (issue 13), test ids ``peer:case``:

- no valid result more than max(0.5 px, 4σ) from the truth (a confident
  wrong answer is never acceptable; a refusal must say why);
- where the peer meets its own assertion, afmdrift meets it too. Needless
  refusals the engine still makes would be xfail(strict) via
  ``_battery.KNOWN_REFUSALS`` (empty today).
"""

from __future__ import annotations

import pytest
from _battery import ALL_CASES, Case, assert_meets_peer, assert_no_confident_wrong_answer, params


@pytest.mark.parametrize("case", params(ALL_CASES, peer_test=False))
def test_no_confident_wrong_answer(case: Case) -> None:
    assert_no_confident_wrong_answer(case)


@pytest.mark.parametrize("case", params(ALL_CASES, peer_test=True))
def test_meets_peer_assertion(case: Case) -> None:
    assert_meets_peer(case)
