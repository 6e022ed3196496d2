"""Which effect is missing: added-variable tests of every candidate term.

Candidates are the library terms not in the model and the generic family
instances of every logged channel and event kind (:func:`family_candidates`);
the tests below are the same for both.

The model (terms M, nonlinear parameters θ_M fitted on the whole run) leaves
level residuals r_a(t_k) = p_a(t_k) − X_M(t_k)β̂_a per axis a. Drift residuals
are strongly autocorrelated (a random walk, slow unmodelled effects), and a
regression of an autocorrelated series on smooth candidates in levels finds
"significant" fits by chance (spurious regression, Granger & Newbold 1974).
So the tests run on AR(1) quasi-differences (Cochrane & Orcutt 1949)::

    ỹ_k = y_k − φ_a·y_{k−1},    Z_k = X_k − φ_a·X_{k−1}

with φ_a the lag-1 autocorrelation of r_a clipped to [0, 1] (φ → 1 is first
differencing). ỹ − Z β̂ is, up to the fit, the one-step prediction error of
an AR(1)-corrected model, the quantity the user cares about.

For each candidate term C not in the model, for each θ of its
:meth:`~afmdrift.model.EffectTerm.nonlinear_grid`, the candidate's basis is
partialled on the model's (Frisch–Waugh–Lovell; the added-variable or partial
regression of Mosteller & Tukey 1977)::

    ε₀ = (I − H_M) ỹ,    Z̃_C = (I − H_M) Z_C(θ),    ε₀ ≈ Z̃_C γ + ε₁

and three pieces of evidence are computed at the θ with the smallest residual
sum of squares over both axes (the best grid point, refined by a bounded 1-D
search between its grid neighbours):

1. **ΔAICc** = AICc(M) − AICc(M + C) (Hurvich & Tsai 1989), Gaussian
   likelihood per axis with its own variance, N = 2n points, the candidate
   counted with its linear coefficients on both axes **plus one parameter
   per scanned nonlinear parameter**.
2. **Wald test of γ = 0** with autocorrelation-robust covariance: Newey–West
   (1987) HAC with the Bartlett kernel and ⌊4(n/100)^{2/9}⌋ lags; to be
   conservative the larger of the HAC and the ordinary covariance is used
   (the HAC estimate collapses for a regressor with a single non-zero row,
   e.g. a step at one event). χ² over both axes; its p-value is multiplied
   by the number of (candidate, θ) pairs tried (Bonferroni).
3. **Blocked cross-validation** (contiguous time blocks dealt out to the
   folds in turn, Bergmeir & Benítez 2012): θ and γ are refitted on the
   other folds, the held-out blocks' RMS error is compared with the
   model's. A term whose columns have no support in some training set
   (e.g. the only offset move falls in the held-out
   block) cannot be cross-validated; it then needs stronger ΔAICc and Wald
   evidence (see :class:`Thresholds`).

A candidate is **significant** when ΔAICc and the Wald test pass and its
out-of-sample error is lower by ``min_cv_drop``: in blocked CV here, or in
the online re-run that :func:`afmdrift.diagnostics.diagnose` makes of the
leading candidates (prequential evaluation, Dawid 1984).

The regression tools themselves (partialling, AICc, the HAC Wald test, the
folds, φ) are in :mod:`afmdrift.diagnostics._regression`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from afmdrift.diagnostics._regression import (
    MIN_FITTED_POINTS,
    WaldTest,
    aicc,
    cv_folds,
    ls_predict,
    ml_phi,
    nonzero_cols,
    partial_out,
    residual_basis,
)
from afmdrift.model import EffectTerm, GenericTerm, History, windowed_design

__all__ = [
    "MAX_CV_RATIO",
    "CandidateResult",
    "ModelDesign",
    "Thresholds",
    "base_basis",
    "cv_unstable",
    "evaluate_candidate",
    "family_candidates",
]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Thresholds:
    """Decision rule for calling a candidate significant.

    Attributes
    ----------
    min_delta_aicc : float
        ΔAICc above which the candidate is preferred (10: "essentially no
        support" for the smaller model, Burnham & Anderson 2002).
    alpha : float
        Family-wise false-alarm level of the HAC Wald test (Bonferroni over
        every candidate and grid point).
    min_cv_drop : float
        Fractional drop of the blocked-CV RMS error required.
    folds : int
        Contiguous CV blocks.
    no_cv_factor : float
        When a term cannot be cross-validated, ΔAICc must exceed
        ``no_cv_factor × min_delta_aicc`` and the Wald p-value
        ``alpha / no_cv_factor``.
    generic_min_drop : float
        The out-of-sample drop a generic term (``channel:``, ``event:``) must
        reach instead of ``min_cv_drop``, in blocked CV or in the online
        re-run; and without blocked CV, a generic term needs the online re-run
        (no in-sample-only route). A generic term is picked from many flexible
        hypotheses (every channel and kind, lags, shapes, one amplitude per
        event), so a few per cent of misfit elsewhere in the model (a
        measurement artefact after an offset move, say) is within its reach:
        it must earn its place by a gain a user would act on.
    min_effect : float
        Effect size first: the fractional drop of the online re-run one-step
        RMS error a candidate must reach to be reported as missing at all (a
        gain a user would act on), whatever its statistical evidence.
    named_margin_aicc : float
        A significant library (named) effect ranks above a significant
        generic term (``channel:``, ``event:``) unless the generic term's
        ΔAICc is higher by more than this (10: the same "essentially no
        support" margin, Burnham & Anderson 2002). A named effect with
        physical parameters is worth more to a user than a generic term that
        fits as well.
    look : int or None
        This diagnosis is the ``look``-th of a sequence over one growing run
        (the daemon's live diagnoses); ``alpha`` is then this look's share of
        ``run_alpha`` (:meth:`at_look`). None: a diagnosis on its own.
    run_alpha : float or None
        With ``look``: the false-alarm level over the whole sequence.
    """

    min_delta_aicc: float = 10.0
    alpha: float = 0.01
    min_cv_drop: float = 0.05
    folds: int = 5
    no_cv_factor: float = 3.0
    generic_min_drop: float = 0.10
    min_effect: float = 0.10
    named_margin_aicc: float = 10.0
    look: int | None = None
    run_alpha: float | None = None

    def at_look(self, look: int) -> Thresholds:
        """The rule for the ``look``-th diagnosis of one growing run (alpha spending).

        The diagnoses of a growing run test the same data again and again;
        each at ``alpha`` would raise a false alarm in most long runs. The
        ``k``-th is tested at ``alpha · 6 / (π² k²)`` instead: since
        ``Σ 6 / (π² k²) = 1``, the chance that any diagnosis of the run, however
        many, calls a candidate significant by chance stays at most ``alpha``
        (a union bound; it needs no planned number of looks).

        Raises
        ------
        ValueError
            ``look`` < 1.
        """
        if look < 1:
            raise ValueError(f"look must be >= 1 (the first diagnosis is 1), got {look}")
        base = self.alpha if self.run_alpha is None else self.run_alpha
        share = 6.0 / (math.pi**2 * look**2)
        return replace(self, alpha=base * share, look=look, run_alpha=base)

    def min_drop(self, *, generic: bool) -> float:
        """The out-of-sample drop required of a named or a generic candidate."""
        return self.generic_min_drop if generic else self.min_cv_drop


@dataclass(frozen=True, slots=True)
class ModelDesign:
    """The model's basis at the observation times, per axis.

    ``t_s`` (n,) are the positions' times and ``samples`` (n, m) the times
    each position averages over (its scan window, :func:`~afmdrift.model.scan_samples`).

    ``builder(params)`` returns the level basis (x, y), each (n, K_a), for
    the model's nonlinear parameters ``params`` (term → name → value);
    ``params`` are the fitted ones; ``grids`` lists (term, parameter, grid)
    of every nonlinear parameter of the model. ``y`` (n, 2) holds the
    measured positions and ``phi`` (2,) the AR(1) coefficients of the
    quasi-differences.
    """

    t_s: FloatArray
    samples: FloatArray
    y: FloatArray
    scan_sign: FloatArray
    phi: FloatArray
    builder: Callable[[dict[str, dict[str, float]]], tuple[FloatArray, FloatArray]]
    params: dict[str, dict[str, float]]
    grids: list[tuple[str, str, FloatArray]]

    @property
    def n_nonlinear(self) -> int:
        return len(self.grids)

    def qd(self, a: FloatArray, axis: int) -> FloatArray:
        """Quasi-difference rows: a[1:] − φ_axis·a[:−1]."""
        return np.asarray(a[1:] - self.phi[axis] * a[:-1], dtype=np.float64)


#: No error estimate from blocked CV when the candidate's cross-validated error is
#: more than this many times the model's: its fit is unstable out of sample
#: (e.g. one amplitude per event with an event near a fold's edge).
MAX_CV_RATIO = 3.0


def cv_unstable(cv_drop: float) -> bool:
    """Whether a change of the cross-validated error means nothing as a per
    cent: the term's error is more than :data:`MAX_CV_RATIO` times the
    model's (``+6188 %`` says only that the fit blew up out of sample)."""
    return 1.0 - cv_drop > MAX_CV_RATIO


@dataclass(slots=True)
class CandidateResult:
    """Evidence for adding one effect term.

    ``params`` holds the fitted nonlinear parameters and the linear
    coefficients per axis (``<coefficient>_x``, ``<coefficient>_y``) in the
    units named by the term. ``driver`` names what drives a generic term
    (empty for a named one); ``channel`` is the logged channel a term reads
    (generic or named, e.g. ``humidity_pct`` for ``humidity``), if any;
    ``discovered`` says what a drift shape read from the drift itself is
    (``{"kind": "jump", "t_s": ..., "step_nm": [x, y]}``, see
    :mod:`afmdrift.diagnostics._discover`), None for every other candidate.
    ``profile`` is (θ value, ΔAICc) over the scanned
    grid of the first nonlinear parameter. ``av`` holds the added-variable
    plot data per axis: (partialled candidate column, partialled response).
    """

    effect: str
    testable: bool
    reason: str = ""
    driver: dict[str, str] = field(default_factory=dict)
    channel: str | None = None
    significant: bool = False
    score: float = math.nan
    delta_aicc: float = math.nan
    wald: float = math.nan
    df: int = 0
    p_value: float = math.nan
    p_bonferroni: float = math.nan
    cv_rmse_base_nm: float = math.nan
    cv_rmse_nm: float = math.nan
    cv_drop: float | None = None
    params: dict[str, float] = field(default_factory=dict)
    nonlinear: dict[str, float] = field(default_factory=dict)
    rmse_after_nm: float | None = None
    rmse_after_kind: str | None = None
    rmse_base_nm: float | None = None
    in_sample_ok: bool = False
    prequential_drop: float | None = None
    p_online: float = math.nan
    p_online_holm: float = math.nan
    alike: list[str] = field(default_factory=list)
    discovered: dict[str, object] | None = None
    profile: list[tuple[float, float]] = field(default_factory=list)
    av: list[tuple[FloatArray, FloatArray]] = field(default_factory=list)

    def evidence(self) -> str:
        """One line summarising the evidence."""
        if not self.testable:
            return f"not testable: {self.reason}"
        if self.cv_drop is None:
            cv = "not cross-validatable"
        elif cv_unstable(self.cv_drop):
            cv = f"blocked-CV error unstable (more than {MAX_CV_RATIO:g} times the model's)"
        elif self.cv_drop >= 0:
            cv = f"blocked-CV error {100 * self.cv_drop:.0f}% lower"
        else:
            cv = f"blocked-CV error {-100 * self.cv_drop:.0f}% higher"
        online = ""
        if self.prequential_drop is not None:
            d = self.prequential_drop
            online = (
                f", online re-run one-step error {100 * d:.0f}% lower"
                if d >= 0
                else f", online re-run one-step error {-100 * d:.0f}% higher"
            )
            if math.isfinite(self.p_online):
                online += (
                    f" (Diebold-Mariano p = {self.p_online:.2g}, Holm {self.p_online_holm:.2g})"
                )
            if self.discovered is not None and self.discovered.get("kind") == "jump":
                online += " (the frames of the jump itself left out of both)"
        return (
            f"ΔAICc = {self.delta_aicc:.1f}, HAC Wald χ²({self.df}) = {self.wald:.1f} "
            f"(p = {self.p_value:.2g}, Bonferroni {self.p_bonferroni:.2g}), {cv}{online}"
        )


def _cand_block(
    term: EffectTerm,
    samples: FloatArray,
    history: History,
    sign: FloatArray,
    params: dict[str, float],
) -> tuple[FloatArray, FloatArray]:
    return (
        windowed_design(term, samples, history, scan_sign=sign, params=params, axis=0),
        windowed_design(term, samples, history, scan_sign=sign, params=params, axis=1),
    )


@dataclass(frozen=True, slots=True)
class _Basis:
    """Quasi-differenced model basis for one θ_M: columns, projector, residuals."""

    params: dict[str, dict[str, float]]
    zm: list[FloatArray]
    qm: list[FloatArray]
    e0: list[FloatArray]

    @property
    def rss(self) -> float:
        return float(sum(e @ e for e in self.e0))


def _basis(design: ModelDesign, params: dict[str, dict[str, float]]) -> _Basis:
    x = design.builder(params)
    zm, qm, e0 = [], [], []
    for a in (0, 1):
        z = design.qd(x[a], a)
        z = z[:, nonzero_cols(z, float(np.abs(z).max()) if z.size else 0.0)]
        q = residual_basis(z)
        zm.append(z)
        qm.append(q)
        e0.append(partial_out(q, design.qd(design.y[:, a], a)))
    return _Basis(params, zm, qm, e0)


def _rss_with(basis: _Basis, zc: Sequence[FloatArray]) -> float:
    total = 0.0
    for a in (0, 1):
        z = partial_out(basis.qm[a], zc[a]) if zc[a].size else zc[a]
        r = basis.e0[a]
        if z.size and z.shape[1]:
            coef, *_ = np.linalg.lstsq(z, r, rcond=1e-10)
            r = r - z @ coef
        total += float(r @ r)
    return total


def optimise_model(design: ModelDesign, zc: Sequence[FloatArray] | None = None) -> _Basis:
    """One coordinate pass over the model's θ grids minimising the quasi-
    differenced RSS (with candidate columns ``zc`` per axis, if given)."""
    extra = list(zc) if zc is not None else [np.zeros((design.t_s.size - 1, 0))] * 2
    params = {k: dict(v) for k, v in design.params.items()}
    best = _basis(design, params)
    best_rss = _rss_with(best, extra)
    for term_name, pname, grid in design.grids:
        for v in grid:
            trial = {k: dict(vv) for k, vv in params.items()}
            trial[term_name][pname] = float(v)
            b = _basis(design, trial)
            rss = _rss_with(b, extra)
            if rss < best_rss:
                best, best_rss, params = b, rss, trial
    return best


def base_basis(design: ModelDesign) -> _Basis:
    """The model's basis with θ_M refitted on the quasi-differences."""
    return optimise_model(design)


#: A grid longer than this (a drift shape searched over every frame boundary or
#: frequency) is scanned and cross-validated with the θ values side by side
#: in arrays, not one least-squares solve after another.
MANY_THETA = 40


def _scan(
    term: EffectTerm,
    design: ModelDesign,
    history: History,
    basis: _Basis,
    grid: list[dict[str, float]],
) -> list[tuple[dict[str, float], list[FloatArray], list[float]]]:
    """Per θ_C: partialled candidate columns and per-axis RSS."""
    if len(grid) > MANY_THETA:
        return _scan_many(term, design, history, basis, grid)
    out = []
    for params in grid:
        blocks = _cand_block(term, design.samples, history, design.scan_sign, params)
        zc, rss1 = [], []
        for a in (0, 1):
            raw = design.qd(np.asarray(blocks[a], dtype=np.float64), a)
            z = partial_out(basis.qm[a], raw)
            ref = float(np.abs(raw).max()) if raw.size else 0.0
            z = z[:, nonzero_cols(z, ref)] if z.size else z
            zc.append(z)
            r = basis.e0[a]
            if z.shape[1]:
                coef, *_ = np.linalg.lstsq(z, r, rcond=1e-10)
                r = r - z @ coef
            rss1.append(float(r @ r))
        out.append((params, zc, rss1))
    return out


def _grid_blocks(
    term: EffectTerm, design: ModelDesign, history: History, grid: list[dict[str, float]]
) -> list[FloatArray]:
    """Quasi-differenced candidate columns of every θ of ``grid`` side by side:
    per axis an array (g, n − 1, c). Needs the same column count at every θ."""
    raw = [_cand_block(term, design.samples, history, design.scan_sign, p) for p in grid]
    out = []
    for a in (0, 1):
        x = np.stack([np.asarray(b[a], dtype=np.float64) for b in raw])
        out.append(np.asarray(x[:, 1:, :] - design.phi[a] * x[:, :-1, :], dtype=np.float64))
    return out


def _small_solve(z: FloatArray, e: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Least squares e ≈ z[g]·c for every g at once: ``z`` (g, m, c), ``e``
    (m,) or (g, m). Returns the coefficients (g, c) and the RSS (g,)."""
    ee = e if e.ndim == 2 else np.broadcast_to(e, z.shape[:2])
    gram = np.einsum("gmc,gmd->gcd", z, z)
    h = np.einsum("gmc,gm->gc", z, ee)
    coef = np.einsum("gcd,gd->gc", np.linalg.pinv(gram, rcond=1e-14, hermitian=True), h)
    r = ee - np.einsum("gmc,gc->gm", z, coef)
    return coef, np.einsum("gm,gm->g", r, r)


def _scan_many(
    term: EffectTerm,
    design: ModelDesign,
    history: History,
    basis: _Basis,
    grid: list[dict[str, float]],
) -> list[tuple[dict[str, float], list[FloatArray], list[float]]]:
    """:func:`_scan` with the θ values side by side in arrays (a long grid)."""
    zs, rss = [], []
    for a, raw in enumerate(_grid_blocks(term, design, history, grid)):
        q = basis.qm[a]
        z = raw - np.einsum("mk,gkc->gmc", q, np.einsum("mk,gmc->gkc", q, raw))
        ref = np.abs(raw).max(axis=(1, 2)) if raw.size else np.zeros(raw.shape[0])
        keep = np.sqrt(np.sum(z * z, axis=1)) > 1e-9 * np.maximum(ref, 1e-30)[:, None]
        z = np.where(keep[:, None, :], z, 0.0)
        _, r = _small_solve(z, basis.e0[a])
        zs.append((z, keep))
        rss.append(np.maximum(r, 0.0))
    return [
        (
            params,
            [zs[a][0][g][:, zs[a][1][g]] for a in (0, 1)],
            [float(rss[0][g]), float(rss[1][g])],
        )
        for g, params in enumerate(grid)
    ]


def _refine(
    term: EffectTerm,
    design: ModelDesign,
    history: History,
    basis: _Basis,
    grid: list[dict[str, float]],
    i_best: int,
    best: tuple[dict[str, float], list[FloatArray], list[float]],
) -> tuple[dict[str, float], list[FloatArray], list[float]]:
    """Bounded 1-D refinement (Brent, on log θ) between the grid neighbours of
    the best grid point; keeps the grid point if the refinement is not better."""
    from scipy.optimize import minimize_scalar

    name = term.nonlinear_params[0].name
    values = [g[name] for g in grid]
    lo = math.log10(values[max(i_best - 1, 0)])
    hi = math.log10(values[min(i_best + 1, len(values) - 1)])
    if hi <= lo:
        return best

    def total(log_v: float) -> float:
        _, zc, rss = _scan(term, design, history, basis, [{name: 10.0**log_v}])[0]
        return sum(rss) if sum(z.shape[1] for z in zc) else math.inf

    res = minimize_scalar(total, bounds=(lo, hi), method="bounded", options={"xatol": 0.005})
    if not (math.isfinite(float(res.fun)) and float(res.fun) < sum(best[2])):
        return best
    return _scan(term, design, history, basis, [{name: 10.0 ** float(res.x)}])[0]


def evaluate_candidate(
    term: EffectTerm,
    design: ModelDesign,
    history: History,
    *,
    n_tests: int,
    thresholds: Thresholds | None = None,
    base: _Basis | None = None,
) -> CandidateResult:
    """Added-variable evidence for adding ``term`` to the model.

    The model's nonlinear parameters θ_M are refitted (one coordinate pass
    over their grids) with the candidate in place, so a model term that
    bent itself to absorb the missing effect gets to straighten out.

    Parameters
    ----------
    term : EffectTerm
        The candidate.
    design : ModelDesign
        The model's basis builder, response and AR(1) coefficients.
    history : History
        Channels and events of the whole run.
    n_tests : int
        Total (candidate, θ) pairs tried in this diagnosis (Bonferroni).
    thresholds : Thresholds
        Decision rule.
    base : _Basis, optional
        :func:`base_basis` of ``design`` (computed if not given).
    """
    n = design.t_s.size - 1
    why = _why_untestable(term, history, n)
    if why is not None:
        return CandidateResult(effect=term.name, testable=False, reason=why)
    thresholds = thresholds or Thresholds()
    b0 = base if base is not None else base_basis(design)
    k_model = sum(q.shape[1] for q in b0.qm) + 2 + design.n_nonlinear
    aicc0 = aicc([float(e @ e) for e in b0.e0], n, k_model)
    grid = term.nonlinear_grid()
    n_theta = len(term.nonlinear_params)
    scan = _scan(term, design, history, b0, grid)
    if not np.isfinite(_totals(scan)).any():
        return CandidateResult(
            effect=term.name,
            testable=False,
            reason="its basis is constant or already spanned by the model on this run",
        )
    design_c, basis, scan = _fit_with_candidate(term, design, history, b0, grid, scan)
    # Candidate parameters count: its linear columns plus one per scanned θ.
    k_base = k_model + n_theta
    profile_d = [
        _delta_aicc(aicc0, rss1, zc, n=n, k_base=k_base) if _n_cols(zc) else math.nan
        for _, zc, rss1 in scan
    ]
    i_best = int(np.argmin(_totals(scan)))
    params, zc, rss1 = scan[i_best]
    d_aicc = profile_d[i_best]
    if n_theta == 1:
        params, zc, rss1 = _refine(term, design_c, history, basis, grid, i_best, scan[i_best])
        d_aicc = _delta_aicc(aicc0, rss1, zc, n=n, k_base=k_base)
    wald = WaldTest.of(zc, basis.e0, n=n, n_tests=n_tests)
    cv_base, cv_cand, cv_ok = _blocked_cv(
        term, design, design_c, history, b0.zm, basis.zm, grid, thresholds.folds
    )
    cv_drop = (1.0 - cv_cand / cv_base) if (cv_ok and cv_base > 0) else None
    in_sample_ok, significant = _decide(
        d_aicc, wald.p_bonferroni, cv_drop, thresholds, generic=isinstance(term, GenericTerm)
    )
    return CandidateResult(
        effect=term.name,
        testable=True,
        significant=bool(significant),
        in_sample_ok=bool(in_sample_ok),
        score=float(d_aicc),
        delta_aicc=float(d_aicc),
        wald=float(wald.chi2),
        df=int(wald.df),
        p_value=wald.p_value,
        p_bonferroni=wald.p_bonferroni,
        cv_rmse_base_nm=float(cv_base),
        cv_rmse_nm=float(cv_cand),
        cv_drop=None if cv_drop is None else float(cv_drop),
        params=_named_params(term, design_c, history, basis, params),
        nonlinear=dict(params),
        profile=_profile(term, scan, profile_d),
        av=_av_data(zc, basis.e0, n),
    )


def _why_untestable(term: EffectTerm, history: History, n: int) -> str | None:
    """Why ``term`` cannot be tested before any fit (missing inputs, too few frames)."""
    why = term.missing(history)
    if why is not None:
        return why
    if n < MIN_FITTED_POINTS:
        return f"only {n + 1} measured frames"
    return None


_Scan = list[tuple[dict[str, float], list[FloatArray], list[float]]]


def _n_cols(zc: Sequence[FloatArray]) -> int:
    """Number of candidate columns left over both axes."""
    return sum(z.shape[1] for z in zc)


def _totals(scan: _Scan) -> list[float]:
    """Per θ_C, the RSS over both axes; inf where the candidate has no column left."""
    return [sum(r) if _n_cols(zc) else math.inf for _, zc, r in scan]


def _fit_with_candidate(
    term: EffectTerm,
    design: ModelDesign,
    history: History,
    b0: _Basis,
    grid: list[dict[str, float]],
    scan: _Scan,
) -> tuple[ModelDesign, _Basis, _Scan]:
    """The model refitted with the candidate in place, and the candidate rescanned.

    θ_M is refitted (when the model has nonlinear parameters) with the best
    grid point of ``scan`` in place; then the model with the candidate gets
    its own φ. Returns the design with that φ, the model basis on it and the
    candidate's scan over ``grid`` against that basis.
    """
    basis = b0
    if design.grids:
        best_params = scan[int(np.argmin(_totals(scan)))][0]
        blocks = _cand_block(term, design.samples, history, design.scan_sign, best_params)
        raw = [design.qd(np.asarray(blocks[a], dtype=np.float64), a) for a in (0, 1)]
        basis = optimise_model(design, raw)
        scan = _scan(term, design, history, basis, grid)
    # One Cochrane–Orcutt step: the model with the candidate gets its own φ, from
    # its level residuals, so the comparison is between the two models' one-step
    # predictions y_k | y_{k-1} (conditional likelihoods of the same data).
    best_params = scan[int(np.argmin(_totals(scan)))][0]
    design_c = replace(design, phi=_level_phi(design, basis.params, term, history, best_params))
    basis = _basis(design_c, basis.params)
    return design_c, basis, _scan(term, design_c, history, basis, grid)


def _delta_aicc(
    aicc0: float, rss1: Sequence[float], zc: Sequence[FloatArray], *, n: int, k_base: int
) -> float:
    """AICc(M) − AICc(M + C): ``k_base`` parameters plus the candidate's columns ``zc``."""
    k_c = _n_cols(zc)
    return aicc0 - aicc(rss1, n, k_base + k_c)


def _profile(term: EffectTerm, scan: _Scan, profile_d: list[float]) -> list[tuple[float, float]]:
    """(θ, ΔAICc) over the grid of the term's first nonlinear parameter; empty if none."""
    if not term.nonlinear_params:
        return []
    pname = term.nonlinear_params[0].name
    return [(float(pp[pname]), float(d)) for (pp, _, _), d in zip(scan, profile_d, strict=True)]


def _av_data(
    zc: Sequence[FloatArray], e0: Sequence[FloatArray], n: int
) -> list[tuple[FloatArray, FloatArray]]:
    """Added-variable plot data per axis: (first candidate column or zeros, residuals)."""
    return [(zc[a][:, 0] if zc[a].shape[1] else np.zeros(n), e0[a]) for a in (0, 1)]


def _decide(
    d_aicc: float,
    p_bonf: float,
    cv_drop: float | None,
    thresholds: Thresholds,
    *,
    generic: bool = False,
) -> tuple[bool, bool]:
    """(in-sample evidence passes, significant) under ``thresholds``.

    Without a blocked-CV drop the in-sample evidence must be stronger by
    ``no_cv_factor``; a ``generic`` term then waits for the online re-run (see
    :class:`Thresholds`).
    """
    in_sample_ok = d_aicc > thresholds.min_delta_aicc and p_bonf < thresholds.alpha
    if cv_drop is not None:
        significant = in_sample_ok and cv_drop >= thresholds.min_drop(generic=generic)
    elif generic:
        significant = False
    else:
        significant = (
            d_aicc > thresholds.no_cv_factor * thresholds.min_delta_aicc
            and p_bonf < thresholds.alpha / thresholds.no_cv_factor
        )
    return in_sample_ok, significant


def _named_params(
    term: EffectTerm,
    design_c: ModelDesign,
    history: History,
    basis: _Basis,
    params: dict[str, float],
) -> dict[str, float]:
    """θ_C, the linear coefficients per axis in the term's units, and the refitted θ_M.

    The coefficients come from the partialled fit on each axis (by
    Frisch–Waugh–Lovell equal to the full quasi-differenced regression's);
    keys are ``<coefficient>_x``/``_y`` and ``model.<term>.<parameter>``.
    """
    blocks = _cand_block(term, design_c.samples, history, design_c.scan_sign, params)
    named: dict[str, float] = dict(params)
    units = term.coefficient_units
    for a, axis in enumerate("xy"):
        raw_a = design_c.qd(np.asarray(blocks[a], dtype=np.float64), a)
        z_full = partial_out(basis.qm[a], raw_a)
        keep = nonzero_cols(z_full, float(np.abs(raw_a).max()) if raw_a.size else 0.0)
        coef_full = np.full(z_full.shape[1], math.nan)
        if keep.any():
            c, *_ = np.linalg.lstsq(z_full[:, keep], basis.e0[a], rcond=1e-10)
            coef_full[keep] = c
        for j, v in enumerate(coef_full):
            if coef_full.size == len(units):  # one name per column
                label = units[j]
            else:  # one amplitude per event: the first name, indexed
                base_name = units[j] if j < len(units) else (units[0] if units else "coef")
                label = base_name if coef_full.size == 1 else f"{base_name}[{j}]"
            named[f"{label}_{axis}"] = float(v)
    for term_name, pname, _ in design_c.grids:
        named[f"model.{term_name}.{pname}"] = float(basis.params[term_name][pname])
    return named


def _level_phi(
    design: ModelDesign,
    params: dict[str, dict[str, float]],
    term: EffectTerm,
    history: History,
    cand_params: dict[str, float],
) -> FloatArray:
    """:func:`ml_phi` of the model (θ_M = ``params``) with the candidate added."""
    xm = design.builder(params)
    xc = _cand_block(term, design.samples, history, design.scan_sign, cand_params)
    return ml_phi(
        design.y,
        [np.hstack([xm[a], np.asarray(xc[a], dtype=np.float64)]) for a in (0, 1)],
    )


def _blocked_cv(
    term: EffectTerm,
    design: ModelDesign,
    design_c: ModelDesign,
    history: History,
    zm_base: list[FloatArray],
    zm: list[FloatArray],
    grid: list[dict[str, float]],
    folds: int,
) -> tuple[float, float, bool]:
    """Blocked-CV RMS one-step error (Euclidean) of the model and of model + term.

    Each model predicts y_k from y_{k-1} with its own φ (``design`` for the
    model, ``design_c`` with the candidate), so both errors are errors of
    predicting the same measured positions.

    θ_C is chosen on each training set; the model's columns are ``zm_base``
    for the model alone and ``zm`` (θ_M refitted with the candidate) with
    it. Returns (base, candidate, evaluable); not evaluable when some fold's
    training data carries none of a column that its test block uses.
    """
    if len(grid) > MANY_THETA:
        return _blocked_cv_many(term, design, design_c, history, zm_base, zm, grid, folds)
    t, sign = design.samples, design.scan_sign
    ytil_base = [design.qd(design.y[:, a], a) for a in (0, 1)]
    ytil = [design_c.qd(design.y[:, a], a) for a in (0, 1)]
    m = ytil[0].size
    labels = cv_folds(m, folds)
    zc_grid = []
    for params in grid:
        blocks = _cand_block(term, t, history, sign, params)
        zc_grid.append([design_c.qd(np.asarray(blocks[a], dtype=np.float64), a) for a in (0, 1)])
    se_base = 0.0
    se_cand = 0.0
    evaluable = True
    for f in range(folds):
        test = labels == f
        train = ~test
        if not test.any():
            continue
        best_rss = math.inf
        best_pred: list[FloatArray] | None = None
        for zc in zc_grid:
            rss = 0.0
            preds = []
            for a in (0, 1):
                full = np.hstack([zm[a], zc[a]])
                supp_train = np.abs(full[train]).max(axis=0) > 0 if full.shape[1] else None
                supp_test = np.abs(full[test]).max(axis=0) > 0 if full.shape[1] else None
                if supp_train is not None and supp_test is not None:
                    if np.any(supp_test & ~supp_train):
                        evaluable = False
                    cols = supp_train
                else:
                    cols = np.zeros(0, dtype=bool)
                ztr = full[train][:, cols]
                coef, *_ = np.linalg.lstsq(ztr, ytil[a][train], rcond=1e-10)
                r = ytil[a][train] - ztr @ coef
                rss += float(r @ r)
                preds.append(full[test][:, cols] @ coef)
            if rss < best_rss:
                best_rss, best_pred = rss, preds
        assert best_pred is not None
        for a in (0, 1):
            base_pred = ls_predict(zm_base[a][train], ytil_base[a][train], zm_base[a][test])
            se_base += float(np.sum((ytil_base[a][test] - base_pred) ** 2))
            se_cand += float(np.sum((ytil[a][test] - best_pred[a]) ** 2))
    return math.sqrt(se_base / m), math.sqrt(se_cand / m), evaluable


def _blocked_cv_many(
    term: EffectTerm,
    design: ModelDesign,
    design_c: ModelDesign,
    history: History,
    zm_base: list[FloatArray],
    zm: list[FloatArray],
    grid: list[dict[str, float]],
    folds: int,
) -> tuple[float, float, bool]:
    """:func:`_blocked_cv` with the θ values side by side in arrays (a long grid).

    On each training set, the model's columns are partialled out
    (Frisch–Waugh–Lovell) and every θ's candidate fit is a small solve; the
    θ with the smallest training RSS over both axes predicts the held-out
    block, as in :func:`_blocked_cv`.
    """
    ytil_base = [design.qd(design.y[:, a], a) for a in (0, 1)]
    ytil = [design_c.qd(design.y[:, a], a) for a in (0, 1)]
    m = ytil[0].size
    labels = cv_folds(m, folds)
    zc = _grid_blocks(term, design_c, history, grid)
    se_base = 0.0
    se_cand = 0.0
    evaluable = True
    for f in range(folds):
        test = labels == f
        train = ~test
        if not test.any():
            continue
        total = np.zeros(len(grid))
        parts = []
        for a in (0, 1):
            zm_a = zm[a]
            supp_m_tr = np.abs(zm_a[train]).max(axis=0) > 0 if zm_a.shape[1] else np.zeros(0, bool)
            supp_m_te = np.abs(zm_a[test]).max(axis=0) > 0 if zm_a.shape[1] else np.zeros(0, bool)
            supp_c_tr = np.abs(zc[a][:, train, :]).max(axis=1) > 0
            supp_c_te = np.abs(zc[a][:, test, :]).max(axis=1) > 0
            if np.any(supp_m_te & ~supp_m_tr) or np.any(supp_c_te & ~supp_c_tr):
                evaluable = False
            xm = zm_a[train][:, supp_m_tr]
            c_tr = np.where(supp_c_tr[:, None, :], zc[a][:, train, :], 0.0)
            y = ytil[a][train]
            pinv_m = np.linalg.pinv(xm, rcond=1e-10) if xm.shape[1] else np.zeros((0, y.size))
            proj_y = xm @ (pinv_m @ y)
            proj_c = np.einsum("mk,gkc->gmc", xm, np.einsum("km,gmc->gkc", pinv_m, c_tr))
            coef, rss = _small_solve(c_tr - proj_c, y - proj_y)
            total += rss
            parts.append((xm, pinv_m, c_tr, coef, supp_m_tr, supp_c_tr))
        g = int(np.argmin(total))
        for a in (0, 1):
            xm, pinv_m, c_tr, coef, supp_m_tr, supp_c_tr = parts[a]
            y = ytil[a][train]
            beta = pinv_m @ (y - c_tr[g] @ coef[g])
            c_te = np.where(supp_c_tr[g][None, :], zc[a][g][test], 0.0)
            pred = zm[a][test][:, supp_m_tr] @ beta + c_te @ coef[g]
            base_pred = ls_predict(zm_base[a][train], ytil_base[a][train], zm_base[a][test])
            se_base += float(np.sum((ytil_base[a][test] - base_pred) ** 2))
            se_cand += float(np.sum((ytil[a][test] - pred) ** 2))
    return math.sqrt(se_base / m), math.sqrt(se_cand / m), evaluable


#: The ``:each`` form (one amplitude per event) is tested up to this many events of a kind.
MAX_EACH_EVENTS = 10


def family_candidates(history: History, model_terms: Sequence[str]) -> list[str]:
    """Term specs of the generic families to test on ``history``.

    One ``channel:<name>`` per logged channel that varies (a second instance
    ``channel:<name>#2``, ``#3``, ... when the model already has that spec,
    e.g. a slow path next to a fast one), and per logged event kind
    ``event:<kind>`` (exponential settling) and ``event:<kind>:log``
    (logarithmic creep), plus their ``:each`` forms (one amplitude per event)
    when the kind was logged more than once and at most
    :data:`MAX_EACH_EVENTS` times (more free amplitudes than that cannot be
    told from fitting noise on a session of a hundred frames). Every spec not
    in ``model_terms``.
    """
    taken = set(model_terms)

    def free(spec: str) -> str:
        if spec not in taken:
            return spec
        k = 2
        while f"{spec}#{k}" in taken:
            k += 1
        return f"{spec}#{k}"

    specs: list[str] = []
    for name in sorted(history.channels):
        if any(c.isspace() or c in ",#=:" for c in name):
            continue  # not expressible as a term spec
        v = np.asarray(history.channels[name], dtype=np.float64)
        v = v[np.isfinite(v)]
        if v.size < 2 or float(np.ptp(v)) <= 0.0:
            continue
        specs.append(free(f"channel:{name}"))
    counts: dict[str, int] = {}
    for e in history.events:
        counts[str(e.kind)] = counts.get(str(e.kind), 0) + 1
    for kind in sorted(counts):
        forms = ["", ":log"]
        if 1 < counts[kind] <= MAX_EACH_EVENTS:
            forms += [":each", ":log:each"]
        for form in forms:
            spec = f"event:{kind}{form}"
            if spec not in taken:
                specs.append(spec)
    return specs
