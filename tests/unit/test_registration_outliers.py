"""The two outlier rules on hand-made block vectors, through the one
block-selection path (``_outliers.select_blocks``)."""

from __future__ import annotations

import numpy as np
import pytest

from afmdrift.registration import RegistrationConfig, _selection
from afmdrift.registration._outliers import MAD_FLOOR_PX, MAX_ITER, select_blocks


def _vectors(rng: np.random.Generator, n_good: int = 40) -> np.ndarray:
    good = np.array([3.0, -2.0]) + rng.normal(0.0, 0.05, (n_good, 2))
    return good


def _valid(v: np.ndarray, keep: np.ndarray, **config: object) -> np.ndarray:
    """The valid blocks among ``keep`` (measured and placed), all on one
    block row (no trend to find)."""
    sel = select_blocks(
        v, keep, keep, keep, row_px=np.zeros(len(v)),
        config=RegistrationConfig.model_validate(config),
    )  # fmt: skip
    assert sel.n_valid == sel.valid.sum()
    return sel.valid


def test_paper_rule_keeps_blocks_within_epsilon_of_the_mean() -> None:
    v = np.array([[0.0, 0.0], [0.2, 0.0], [-0.2, 0.0], [0.0, 0.3], [1.6, 0.0]])
    keep = np.ones(5, dtype=bool)
    # mean = (0.32, 0.06): block 4 is 1.28 px away.
    out = _valid(v, keep, outlier_rule="paper", epsilon_px=1.0)
    assert out.tolist() == [True, True, True, True, False]
    # Blocks already excluded stay excluded and do not enter the mean.
    keep[1] = False
    assert not _valid(v, keep, outlier_rule="paper", epsilon_px=10.0)[1]


def test_paper_rule_is_dragged_by_a_gross_outlier_while_mad_is_not() -> None:
    """Documented weakness of the paper's rule: one wild block moves the mean
    so that good blocks fall outside epsilon."""
    rng = np.random.default_rng(0)
    v = np.vstack([_vectors(rng), [[40.0, 30.0]]])
    keep = np.ones(len(v), dtype=bool)
    paper = _valid(v, keep, outlier_rule="paper", epsilon_px=0.5)
    mad = _valid(v, keep, outlier_rule="mad", mad_threshold=3.5)
    assert paper[:-1].sum() < 10  # most good blocks lost
    assert mad[:-1].all()
    assert not mad[-1]


def test_mad_rule_iterates_and_rejects_a_cluster_of_outliers() -> None:
    rng = np.random.default_rng(1)
    good = _vectors(rng, 48)
    pushed = np.array([5.0, -3.0]) + rng.normal(0.0, 0.05, (16, 2))  # 25 % moved together
    v = np.vstack([good, pushed])
    out = _valid(v, np.ones(len(v), dtype=bool), outlier_rule="mad", mad_threshold=3.5)
    assert out[:48].sum() >= 46
    assert not out[48:].any()


def test_mad_floor_keeps_identical_vectors() -> None:
    """Regression guard: noise-free blocks agree to 1e-6 px; a zero MAD must
    not turn rounding noise into outliers."""
    v = np.tile([1.0, 2.0], (20, 1)) + np.linspace(0, 1e-6, 20)[:, None]
    v[3] += MAD_FLOOR_PX  # a twentieth of a pixel off: still the same motion
    out = _valid(v, np.ones(20, dtype=bool), outlier_rule="mad", mad_threshold=3.5)
    assert out.all()


def test_too_few_blocks_are_left_alone() -> None:
    v = np.array([[0.0, 0.0], [5.0, 5.0]])
    keep = np.array([True, True])
    assert _valid(v, keep, outlier_rule="mad").tolist() == [True, True]
    assert not _valid(v, np.zeros(2, dtype=bool), outlier_rule="paper").any()


def test_the_trend_over_the_rows_replaces_one_mean_where_the_drift_changed() -> None:
    """With the MAD rule, blocks whose rows were scanned at different times
    are judged about a trend over the rows: a drift that sped up during the
    scan (here 0.5 px per block row) keeps every block and reports the
    residual spread, where one mean would call the rows outliers."""
    rng = np.random.default_rng(2)
    rows = np.repeat(np.arange(8) * 50.0 + 64.0, 8)
    v = np.column_stack([3.0 + 0.01 * rows, -2.0 + 0.0 * rows]) + rng.normal(0.0, 0.03, (64, 2))
    keep = np.ones(64, dtype=bool)
    sel = select_blocks(v, keep, keep, keep, row_px=rows, config=RegistrationConfig())
    assert sel.n_valid == 64
    assert max(sel.spread_px) < 0.05
    assert sel.mean_px[0] == pytest.approx(v[:, 0].mean(), rel=1e-12)
    paper = select_blocks(
        v, keep, keep, keep, row_px=rows, config=RegistrationConfig(outlier_rule="paper")
    )
    assert paper.spread_px[0] > 0.5  # one mean: the rows' spread


def _reject_mad_numpy(vec: np.ndarray, keep: np.ndarray, threshold: float) -> np.ndarray:
    """The rule of the module docstring, stated with NumPy."""
    out = keep.copy()
    for _ in range(20):
        if out.sum() < 3:
            return out
        sel = vec[out]
        med = np.median(sel, axis=0)
        scale = 1.4826 * np.maximum(np.median(np.abs(sel - med), axis=0), MAD_FLOOR_PX)
        new = keep & (np.abs(vec - med) / scale <= threshold).all(axis=1)
        if np.array_equal(new, out):
            return out
        out = new
    return out


@pytest.mark.parametrize("seed", range(20))
def test_compiled_mad_rule_matches_its_numpy_statement(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 80))
    vec = rng.normal(0.0, 0.05, (n, 2)) + rng.normal(0.0, 3.0, 2)
    bad = rng.random(n) < rng.uniform(0.0, 0.4)
    vec[bad] += rng.normal(0.0, 5.0, (int(bad.sum()), 2))
    keep = rng.random(n) < 0.9
    out = np.empty(n, dtype=bool)
    rule = _selection.MadRule(threshold=3.5, floor=MAD_FLOOR_PX, max_iter=MAX_ITER)
    _selection.reject_mad(vec, keep, rule, out)
    np.testing.assert_array_equal(out, _reject_mad_numpy(vec, keep, 3.5))
