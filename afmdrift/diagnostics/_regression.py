"""The regression tools of the candidate tests, on AR(1) quasi-differences.

Partialling a basis out of another (Frisch–Waugh–Lovell), the small-sample
AIC (Hurvich & Tsai 1989), the conservative HAC Wald test with Newey–West
lags (1987, 1994), the contiguous folds of blocked cross-validation (Bergmeir
& Benítez 2012) and the AR(1) coefficient φ that maximises a model's
conditional likelihood. :mod:`afmdrift.diagnostics._candidates` explains
where each is used.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import special

__all__ = [
    "MIN_FITTED_POINTS",
    "PHI_GRID",
    "WaldTest",
    "aicc",
    "cv_folds",
    "forecast_comparison",
    "ls_predict",
    "ml_phi",
    "newey_west_lags",
    "nonzero_cols",
    "ols_hac",
    "partial_out",
    "residual_basis",
]

FloatArray = npt.NDArray[np.float64]


#: The fewest points a test here is made on: the added-variable fits' AR(1)
#: quasi-differences (frames − 1 per axis) and the Diebold–Mariano test's
#: frames compared. Below it the Newey–West covariance has a single lag and
#: a handful of residual degrees of freedom once the model's columns, the
#: candidate's and its nonlinear parameters are fitted, so the tests' p-values
#: and AICc mean nothing.
MIN_FITTED_POINTS = 10


def newey_west_lags(n: int) -> int:
    """⌊4(n/100)^{2/9}⌋, Newey & West (1994) rule of thumb for the Bartlett kernel."""
    return max(1, math.floor(4.0 * (n / 100.0) ** (2.0 / 9.0)))  # type: ignore[no-any-return]


def forecast_comparison(e_base: FloatArray, e_new: FloatArray) -> tuple[float, int]:
    """One-sided p-value that ``e_new`` predicts better than ``e_base``, and the
    number of frames compared.

    The Diebold–Mariano test (Diebold & Mariano 1995) on the loss differential
    d_k = |e_base,k|² − |e_new,k|² of two models' one-step errors over the same
    frames (rows (m, 2), NaN rows left out): t = d̄ / se(d̄) with a Newey–West
    (Bartlett) variance, ⌊4(m/100)^{2/9}⌋ lags, so the autocorrelation of the
    errors is paid for; with the small-sample correction of Harvey, Leybourne &
    Newbold (1997) and Student's t with m − 1 degrees of freedom. Both errors
    are prequential (each frame predicted before the model saw it), so the
    test compares what the service would have predicted; for nested models it
    is conservative (Clark & McCracken 2001), which keeps its false-alarm level.
    NaN when fewer than :data:`MIN_FITTED_POINTS` frames or no variance.
    """
    a = np.asarray(e_base, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(e_new, dtype=np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    d = np.sum(a[ok] ** 2, axis=1) - np.sum(b[ok] ** 2, axis=1)
    m = int(d.size)
    if m < MIN_FITTED_POINTS:
        return math.nan, m
    dc = d - d.mean()
    lags = min(newey_west_lags(m), m - 1)
    var = float(dc @ dc) / m
    for j in range(1, lags + 1):
        var += 2.0 * (1.0 - j / (lags + 1.0)) * float(dc[j:] @ dc[:-j]) / m
    if not var > 0:
        return math.nan, m
    stat = float(d.mean()) / math.sqrt(var / m)
    h = lags + 1
    stat *= math.sqrt((m + 1 - 2 * h + h * (h - 1) / m) / m)
    return float(special.stdtr(m - 1, -stat)), m  # Student's t survival


def nonzero_cols(z: FloatArray, ref: float) -> npt.NDArray[np.bool_]:
    out: npt.NDArray[np.bool_] = np.sqrt(np.sum(z * z, axis=0)) > 1e-9 * max(ref, 1e-30)
    return out


def residual_basis(z: FloatArray) -> FloatArray:
    """Orthonormal basis Q (n, r) of the column space of ``z``."""
    if z.shape[1] == 0:
        return np.zeros((z.shape[0], 0))
    u, s, _ = np.linalg.svd(z, full_matrices=False)
    tol = s.max() * max(z.shape) * np.finfo(float).eps if s.size else 0.0
    return np.asarray(u[:, s > tol], dtype=np.float64)


def partial_out(q: FloatArray, a: FloatArray) -> FloatArray:
    return np.asarray(a - q @ (q.T @ a), dtype=np.float64)


def aicc(rss: Sequence[float], n: int, k: int) -> float:
    total_n = n * len(rss)
    ll = sum(-0.5 * n * (math.log(2 * math.pi * max(r, 1e-300) / n) + 1.0) for r in rss)
    if total_n - k - 1 <= 0:
        return math.inf
    return -2.0 * ll + 2.0 * k + 2.0 * k * (k + 1) / (total_n - k - 1)


def ols_hac(z: FloatArray, y: FloatArray, lags: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Least squares of ``y`` on the columns of ``z`` (full column rank, no
    constant added): the coefficients, their OLS covariance s²(ZᵀZ)⁻¹ with
    s² = RSS/(n−k), and their Newey–West (1987) HAC covariance with Bartlett
    weights 1 − j/(lags+1) and the small-sample factor n/(n−k).

    (The same numbers as statsmodels' ``OLS(y, z).fit()`` and its
    ``get_robustcov_results(cov_type="HAC", maxlags=lags,
    use_correction=True)``, which the tests check; computed here because
    importing statsmodels' regression, with pandas, took a second of every
    diagnosis.)
    """
    n, k = z.shape
    zz_inv = np.linalg.inv(z.T @ z)
    gamma = zz_inv @ (z.T @ y)
    r = y - z @ gamma
    v_ols = zz_inv * (float(r @ r) / (n - k))
    g = z * r[:, None]
    s = g.T @ g
    for j in range(1, min(lags, n - 1) + 1):
        c = g[j:].T @ g[:-j]
        s += (1.0 - j / (lags + 1.0)) * (c + c.T)
    v_hac = zz_inv @ s @ zz_inv * (n / (n - k))
    return (
        np.asarray(gamma, dtype=np.float64),
        np.asarray(v_ols, dtype=np.float64),
        np.asarray(v_hac, dtype=np.float64),
    )


def _wald(z: FloatArray, e0: FloatArray, lags: int) -> tuple[float, int, FloatArray]:
    """Conservative Wald statistic of γ in e0 ≈ z γ (HAC vs OLS covariance).

    A rank-deficient ``z`` (a candidate column the model's basis already
    spans, partialled to zero) is tested in its column space: the degrees of
    freedom are its rank, not its column count.
    """
    n, k = z.shape
    if k == 0 or n <= k + 1:
        return 0.0, 0, np.zeros(0)
    u, sv, _ = np.linalg.svd(z, full_matrices=False)
    rank = int(np.sum(sv > sv[0] * 1e-10)) if sv.size and sv[0] > 0 else 0
    if rank == 0:
        return 0.0, 0, np.zeros(0)
    if rank < k:
        z, k = u[:, :rank] * sv[:rank], rank
    gamma, v_ols, v_hac = ols_hac(z, e0, lags)
    w_ols = float(gamma @ np.linalg.pinv(v_ols) @ gamma)
    w_hac = float(gamma @ np.linalg.pinv(v_hac) @ gamma)
    return min(w_ols, w_hac), k, gamma


def cv_folds(m: int, folds: int) -> npt.NDArray[np.int64]:
    """Fold label of each of ``m`` rows: contiguous blocks dealt out in turn.

    Blocks are ``max(3, m // (4·folds))`` rows long and block j goes to fold
    j mod ``folds``, so every training set spans the whole record (no
    extrapolation to an unseen start or end, which would fail transient
    effects such as warm-up for the wrong reason) while each held-out block
    is contiguous.
    """
    length = max(3, m // (4 * folds))
    return np.asarray((np.arange(m) // length) % folds, dtype=np.int64)


def ls_predict(z_train: FloatArray, y_train: FloatArray, z_test: FloatArray) -> FloatArray:
    if z_train.shape[1] == 0:
        return np.zeros(z_test.shape[0])
    coef, *_ = np.linalg.lstsq(z_train, y_train, rcond=1e-10)
    return np.asarray(z_test @ coef, dtype=np.float64)


@dataclass(frozen=True, slots=True)
class WaldTest:
    """Conservative HAC Wald test of γ = 0 over both axes, with its Bonferroni p-value."""

    chi2: float
    df: int
    p_value: float
    p_bonferroni: float

    @classmethod
    def of(
        cls, zc: Sequence[FloatArray], e0: Sequence[FloatArray], *, n: int, n_tests: int
    ) -> WaldTest:
        """The test of candidate columns ``zc`` against model residuals ``e0``.

        Parameters
        ----------
        zc : sequence of two ndarrays, shapes (n, K_a)
            Partialled candidate columns per axis.
        e0 : sequence of two ndarrays, shape (n,)
            Partialled model residuals per axis, nm.
        n : int
            Quasi-differenced rows (sets the Newey–West lags).
        n_tests : int
            (candidate, θ) pairs tried in the diagnosis (Bonferroni factor).
        """
        lags = newey_west_lags(n)
        wald = 0.0
        df = 0
        for a in (0, 1):
            w, k, _ = _wald(zc[a], e0[a], lags)
            wald += w
            df += k
        p = float(special.chdtrc(df, wald)) if df else 1.0
        return cls(wald, df, p, min(1.0, p * max(n_tests, 1)))


#: AR(1) coefficients searched for each model's conditional likelihood.
PHI_GRID = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 1.0])


def ml_phi(y: FloatArray, x: Sequence[FloatArray]) -> FloatArray:
    """Per axis, the φ of :data:`PHI_GRID` that maximises the conditional
    Gaussian likelihood of y_k | y_{k−1} (minimum quasi-differenced RSS).

    Parameters
    ----------
    y : ndarray, shape (n, 2)
    x : sequence of two ndarrays, shapes (n, K_a)
        Level basis per axis.
    """
    phi = np.zeros(2)
    for a in (0, 1):
        best = math.inf
        for f in PHI_GRID:
            z = x[a][1:] - f * x[a][:-1]
            yt = y[1:, a] - f * y[:-1, a]
            keep = nonzero_cols(z, float(np.abs(z).max()) if z.size else 0.0)
            r = yt
            if keep.any():
                coef, *_ = np.linalg.lstsq(z[:, keep], yt, rcond=1e-10)
                r = yt - z[:, keep] @ coef
            rss = float(r @ r)
            if rss < best:
                best, phi[a] = rss, float(f)
    return phi
