"""Peer battery, pystackreg: pystackreg's PC12 stack registration
(translation, reference 'previous').

The cases (facts of each peer test, our substitutes for data we do not
have, and the peer's tolerance) are defined once in ``_battery.py``, which
``benchmarks/peer_battery.py`` runs too. Two checks per case (issue 13):

- no valid result more than max(0.5 px, 4σ) from the truth (a confident
  wrong answer is never acceptable; a refusal must say why);
- where the peer meets its own assertion, afmdrift meets it too. Needless
  refusals the engine still makes are xfail(strict) via
  ``_battery.KNOWN_REFUSALS``.
"""

from __future__ import annotations

import pytest
from _battery import (
    Case,
    assert_meets_peer,
    assert_no_confident_wrong_answer,
    cases_of,
    params,
)

CASES = cases_of("pystackreg")


@pytest.mark.parametrize("case", params(CASES, peer_test=False))
def test_no_confident_wrong_answer(case: Case) -> None:
    assert_no_confident_wrong_answer(case)


@pytest.mark.parametrize("case", params(CASES, peer_test=True))
def test_meets_peer_assertion(case: Case) -> None:
    assert_meets_peer(case)
