"""Physics-informed drift predictor: a sum of terms from the effects library.

Model, per axis a ∈ {x, y}::

    p_a(t) = Σ_terms B_term(t; θ_term, a)·β_term,a  [+ intercept]  + residual_a(t)

with B the basis functions of :mod:`afmdrift.model._effects`. The fit, redone
at every frame over all points (optionally down-weighted with age by
exp(−age/``memory_s``)):

0. **Which points**: the most recent ``max_points`` observations.
1. **Which terms**: a configured term whose inputs are absent (channel not
   logged, no event of its kind) is left out and logged once. Terms enter in
   configured order once there are ``min_points_per_column`` points per basis
   column, so an early fit is never under-determined.
2. **Nonlinear parameters θ** (time constants) are shared by both axes. Each
   is found by coordinate descent: a scan of the term's log grid
   (:meth:`EffectTerm.nonlinear_grid`), then a bounded 1-D refinement
   (Brent, on log θ, between the grid neighbours of the best point); the
   objective is the weighted residual sum of squares of both axes. θ is
   searched again only once the points grew by ``search_growth`` (10 %)
   since its last search, or a term's support or the event log changed,
   and then from where it was (a warm start: a refinement within one grid
   step, the whole grid only when the optimum left it); the fits in between
   solve step 3 alone, in closed form.
3. **Linear coefficients β** by weighted least squares with weights
   1/max(σ, ``sigma_floor_nm``)², on column-normalised designs (rank-deficient
   directions get the minimum-norm solution). Their covariance s²(XᵀWX)⁺ gives
   the parametric part of the prediction uncertainty.
4. **Residual**: ``none``; ``ar1``, r̂(t_n + h·Δ) = φ^h·r_n with φ the lag-1
   regression coefficient of the recent in-sample residuals clipped to [0, 1]
   (slow unmodelled wander persists, white noise does not; φ = 1 until
   eight residuals exist); or ``nn``, the
   paper's network trained online on the residual series.

Scan direction at future times is extrapolated from the last frames
(alternating up/down continues to alternate).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from afmdrift.config import NNConfig, PhysicsConfig
from afmdrift.model._base import History, Observation, OffsetPlay, Prediction
from afmdrift.model._baselines import ObservationLog, _LoggingPredictor, as_times
from afmdrift.model._effects import EffectTerm, warm_up_effects, windowed_design
from afmdrift.model._terms import resolve_terms
from afmdrift.records import ScanDirection

__all__ = [
    "FitResult",
    "PhysicsNNPredictor",
    "PhysicsPredictor",
    "solve_wls",
    "weighted_rss",
]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: While fewer points than this are fitted, θ is searched at every fit (the
#: early fits move the most).
_ALWAYS_SEARCH_BELOW = 20


@dataclass(frozen=True, slots=True)
class FitResult:
    """Weighted least-squares solution of one axis.

    ``coef`` (K,) for the kept columns ``keep`` (bool mask over the full
    design), ``cov`` (K, K), ``wrss`` the weighted residual sum of squares.
    """

    coef: FloatArray
    cov: FloatArray
    keep: npt.NDArray[np.bool_]
    wrss: float


def weighted_rss(x: FloatArray, y: FloatArray, w: FloatArray) -> float:
    """Weighted residual sum of squares of the WLS fit of y on X (the search objective)."""
    a, b, _ = _whitened(x, y, w)
    r = b - a @ _determined_lstsq(a, b)
    return float(r @ r)


def _whitened(
    x: FloatArray, y: FloatArray, w: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(A, b, norms)``: the weighted design with columns of unit norm (a zero
    column stays zero, its norm taken as 1), the weighted data, the norms."""
    sw = np.sqrt(w)
    a = x * sw[:, None]
    norms = np.sqrt(np.sum(a * a, axis=0))
    norms = np.where(norms > 0, norms, 1.0)
    return a / norms, y * sw, norms


#: A direction of the (column-normalised) design whose singular value is below
#: this fraction of the largest is left out of the fit (:func:`_determined_lstsq`).
ILL_CONDITIONED = 1e-2


def _determined_lstsq(a: FloatArray, b: FloatArray) -> FloatArray:
    """Least squares ``a·c ≈ b`` (columns of unit norm) without its ill-conditioned directions.

    The truncated SVD (Hansen 1987, BIT 27:534): through a = U·S·Vᵀ, a
    direction i with s_i < :data:`ILL_CONDITIONED`·s_max gets coefficient 0.
    There the ordinary coefficient is u_iᵀb / s_i: terms nearly alike over
    the frames fitted (``thermal`` beside a channel response with a lag of
    seconds; an intercept, a trend and a channel that has drifted slowly so
    far) get huge opposite coefficients, and the prediction one frame later,
    where the columns part, is off by hundreds or thousands of nm. Leaving
    the direction out keeps every direction the data determine well.
    """
    u, sv, vt = np.linalg.svd(a, full_matrices=False)
    if sv.size == 0:
        return np.zeros(a.shape[1])
    kept = (sv > 0.0) & (sv >= ILL_CONDITIONED * sv[0])
    coef: FloatArray = vt.T @ np.where(kept, (u.T @ b) / np.where(kept, sv, 1.0), 0.0)
    return coef


def solve_wls(x: FloatArray, y: FloatArray, w: FloatArray) -> FitResult:
    """Weighted least squares y ≈ X·β with weights ``w``, dropping zero columns
    and the ill-conditioned directions (:func:`_determined_lstsq`).

    Parameters
    ----------
    x : ndarray, shape (n, K)
    y : ndarray, shape (n,)
    w : ndarray, shape (n,)
        Non-negative weights (1/σ²).
    """
    keep = np.any(np.abs(x) > 1e-12, axis=0)
    an, b, norms = _whitened(x[:, keep], y, w)
    coef_n = _determined_lstsq(an, b)
    coef = coef_n / norms
    resid = b - an @ coef_n
    wrss = float(resid @ resid)
    n, k = an.shape
    s2 = wrss / (n - k) if n > k else 1.0
    cov = s2 * np.linalg.pinv(an.T @ an, rcond=1e-10) / np.outer(norms, norms)
    return FitResult(coef, cov, keep, wrss)


def future_scan_sign(t_s: FloatArray, obs_t_s: FloatArray, obs_sign: FloatArray) -> FloatArray:
    """Scan sign (+1 up, −1 down) at ``t_s``: the nearest frame's in the past,
    extrapolated frame by frame (alternating if the last two differ) after it."""
    out = np.empty_like(t_s)
    if obs_t_s.size == 0:
        out[:] = 1.0
        return out
    idx = np.clip(np.searchsorted(obs_t_s, t_s), 0, obs_t_s.size - 1)
    prev = np.clip(idx - 1, 0, obs_t_s.size - 1)
    nearest = np.where(np.abs(obs_t_s[prev] - t_s) <= np.abs(obs_t_s[idx] - t_s), prev, idx)
    out[:] = obs_sign[nearest]
    after = t_s > obs_t_s[-1]
    if after.any():
        alternating = obs_sign.size >= 2 and obs_sign[-1] != obs_sign[-2]
        if alternating:
            step = float(np.median(np.diff(obs_t_s)))
            k = np.rint((t_s[after] - obs_t_s[-1]) / step).astype(np.int64)
            out[after] = obs_sign[-1] * np.where(k % 2 == 0, 1.0, -1.0)
        else:
            out[after] = obs_sign[-1]
    return out


def _conform(x: FloatArray, k: int) -> FloatArray:
    """Trim or zero-pad ``x`` to ``k`` columns.

    A term with one column per event (``tip_change``) gains a column when an
    event is logged after the last fit; its amplitude is unknown until the next
    fit, so it contributes nothing until then.
    """
    if x.shape[1] == k:
        return x
    if x.shape[1] > k:
        return x[:, :k]
    return np.hstack([x, np.zeros((x.shape[0], k - x.shape[1]))])


class PhysicsPredictor(_LoggingPredictor):
    """Sum of library effect terms with online-fitted physical parameters.

    Parameters
    ----------
    config : PhysicsConfig
        Terms, plugins, residual model, weighting.
    nn_config : NNConfig
        Network used when ``config.residual == "nn"``.
    """

    name = "physics"

    def __init__(
        self, config: PhysicsConfig | None = None, *, nn_config: NNConfig | None = None
    ) -> None:
        super().__init__()
        self.config = config or PhysicsConfig()
        self.nn_config = nn_config or NNConfig()
        classes = resolve_terms(self.config.terms, self.config.plugins)
        self.terms: list[EffectTerm] = [cls() for cls in classes]
        self.params: dict[str, dict[str, float]] = {t.name: t.default_params() for t in self.terms}
        self.active: list[str] = []
        self.fits: list[FitResult] = []
        self.columns: list[list[tuple[str, int]]] = []
        self.add_intercept = False
        self.phi = np.zeros(2)
        self.last_residual = np.zeros(2)
        self.residual_sd = np.full(2, math.nan)
        self._missing_logged: set[str] = set()
        # The terms' kernels compile now, not at the first fit. scipy.optimize
        # (0.3-0.6 s to import) loads with the first θ refinement
        # (:meth:`_refined`), not with every model (a drift log's trend needs none).
        warm_up_effects()
        self.residual_net = None
        if self.config.residual == "nn":
            from afmdrift.model._nn import NNSeriesModel

            self.residual_net = NNSeriesModel(self.nn_config)
        # The last fit's in-sample residuals (n, 2), nm.
        self._residuals: FloatArray = np.zeros((0, 2))
        self.min_points_to_predict = 2
        # Where θ was last searched: the number of points, and the active terms.
        self._searched_at = 0
        self._searched_terms: tuple[str, ...] = ()

    # ----------------------------------------------------------------- design
    def _term(self, name: str) -> EffectTerm:
        for t in self.terms:
            if t.name == name:
                return t
        raise KeyError(name)

    def design_blocks(
        self,
        t_s: FloatArray,
        history: History,
        scan_sign: FloatArray,
        axis: int,
        *,
        active: Sequence[str] | None = None,
        params: dict[str, dict[str, float]] | None = None,
    ) -> list[tuple[str, FloatArray]]:
        """(name, basis block) of each active term, led by ``intercept`` if needed.

        ``t_s`` is (n,) for points or (n, m) sample times of scan windows
        (:func:`~afmdrift.model._effects.windowed_design`)."""
        names = self.active if active is None else active
        prm = self.params if params is None else params
        blocks: list[tuple[str, FloatArray]] = []
        if self._needs_intercept(names):
            blocks.append(("intercept", np.ones((t_s.shape[0], 1))))
        for name in names:
            block = windowed_design(
                self._term(name), t_s, history, scan_sign=scan_sign, params=prm[name], axis=axis
            )
            blocks.append((name, block))
        return blocks

    def _supported(self, blocks: dict[str, FloatArray]) -> list[FloatArray]:
        """The search's blocks with every column that is non-zero on fewer
        than its term's :attr:`~afmdrift.model.EffectTerm.min_column_support`
        fitted points set to zero, so that θ is not bent to fit noise with a
        young column: a settling response to an event that has just happened
        is a tiny column on one or two frames, and its amplitude there is noise
        divided by a small number. The final fit keeps such a column where its
        amplitude is clearly determined (:meth:`_weak_new_columns`)."""
        return [
            np.where(young[None, :], 0.0, b) if young.any() else b
            for b, young in zip(blocks.values(), self._young_columns(blocks), strict=True)
        ]

    def _young_columns(self, blocks: dict[str, FloatArray]) -> list[BoolArray]:
        """Per block, its columns non-zero on at least one but fewer than its
        term's :attr:`~afmdrift.model.EffectTerm.min_column_support` points."""
        out = []
        for name, b in blocks.items():
            need = 1 if name == "intercept" else self._term(name).min_column_support
            if need <= 1:  # most terms: no count on the search's hot path
                out.append(np.zeros(b.shape[1], dtype=bool))
                continue
            nonzero = np.count_nonzero(np.abs(b) > 1e-12, axis=0)
            out.append((nonzero > 0) & (nonzero < need))
        return out

    def _weak_new_columns(self, blocks: dict[str, FloatArray], fit: FitResult) -> BoolArray:
        """Columns (over the full design) still short of their term's
        :attr:`~afmdrift.model.EffectTerm.min_column_support` whose coefficient
        is not clearly determined (|β| < 3σ_β): held at 0 in the final fit.
        Clean data determine a new event's response from its first frame;
        noisy data wait until it shows."""
        parts = self._young_columns(blocks)
        young = np.concatenate(parts) if parts else np.zeros(0, dtype=bool)
        if not young.any():
            return young
        coef = np.zeros(young.size)
        se = np.full(young.size, np.inf)
        coef[fit.keep] = fit.coef
        se[fit.keep] = np.sqrt(np.maximum(np.diag(fit.cov), 0.0))
        return young & ~(np.abs(coef) >= 3.0 * se)

    def _needs_intercept(self, names: Sequence[str]) -> bool:
        return not any(self._term(n).provides_intercept for n in names)

    # -------------------------------------------------------------------- fit
    def update(self, obs: Observation, history: History) -> None:
        self.log.append(obs, self._one_step_error(obs, history))
        self._fit(history)

    def _weights(self) -> FloatArray:
        sigma = np.maximum(np.asarray(self.log.sigma_nm), self.config.sigma_floor_nm)
        w = 1.0 / sigma**2
        if self.config.memory_s > 0:
            t = self.log.t()
            w = w * np.exp(-(t[-1] - t) / self.config.memory_s)
        return np.asarray(w, dtype=np.float64)

    def _choose_active(self, history: History, t: FloatArray, sign: FloatArray) -> list[str]:
        # The blocks built here at the current θ serve the fit when θ is not searched.
        self._built: dict[tuple[str, int], FloatArray] = {}
        n = t.shape[0]
        chosen: list[str] = []
        columns = 0
        for term in self.terms:
            why = term.missing(history)
            if why is not None:
                if term.name not in self._missing_logged:
                    self._missing_logged.add(term.name)
                    _log.info("physics: term %r left out: %s", term.name, why)
                continue
            k = 0
            constant = False
            for axis in (0, 1):
                block = windowed_design(
                    term, t, history, scan_sign=sign, params=self.params[term.name], axis=axis
                )
                self._built[(term.name, axis)] = block
                nonzero = np.any(np.abs(block) > 1e-12, axis=0)
                k = max(k, int(np.count_nonzero(nonzero)))
                if n >= 2 and np.any(nonzero & (np.ptp(block, axis=0) < 1e-12)):
                    constant = True
            if constant and not term.provides_intercept:
                # A constant column duplicates the intercept (e.g. scan_direction
                # when every frame is scanned up): not identifiable, left out.
                continue
            extra = 1 if (not chosen and not term.provides_intercept) else 0
            # The first term may be exactly determined (two points fix a trend);
            # later ones need min_points_per_column points per column.
            ratio = 1.0 if not chosen else self.config.min_points_per_column
            if n >= ratio * (columns + k + extra):
                chosen.append(term.name)
                columns += k + extra
        return chosen

    def _fit(self, history: History) -> None:
        # The most recent max_points observations (bounded cost per frame at
        # HS-AFM frame rates); older ones are down-weighted by memory_s anyway.
        k0 = max(len(self.log) - self.config.max_points, 0)
        t = self.log.t()[k0:]
        # Each position is fitted as the mean of p over its scan window.
        ts = self.log.samples()[k0:]
        xy = self.log.xy()[k0:]
        sign = np.asarray(self.log.scan_sign[k0:], dtype=np.float64)
        w = self._weights()[k0:]
        active = self._choose_active(history, ts, sign)
        params = {k: dict(v) for k, v in self.params.items()}
        nonlinear = [(name, p) for name in active for p in self._term(name).nonlinear_params]
        searched = False
        inputs = self._inputs(active, history)
        if nonlinear and t.size >= 3 and self._search_due(t.size, inputs):
            searched = True
            # A term searched before starts where it was (a warm start): its
            # first pass refines around that value, and scans the whole grid
            # only when the optimum left the neighbourhood.
            warm = {key.rpartition("|")[0] for key in set(self._searched_terms) & set(inputs)}
            self._searched_at = t.size
            self._searched_terms = inputs
            # Blocks of every term at the current θ; a scan only rebuilds its own term.
            blocks = [
                dict(self.design_blocks(ts, history, sign, axis, active=active, params=params))
                for axis in (0, 1)
            ]
            # A term whose columns are zero on every point (creep before any
            # move) says nothing about its θ: it keeps its value. With one θ
            # left, a second coordinate pass would repeat the first.
            nonlinear = [(name, p) for name, p in nonlinear if any(b[name].any() for b in blocks)]
            passes = self.config.refine_passes if len(nonlinear) > 1 else 1
            for pass_no in range(passes):
                first_pass = pass_no == 0
                for name, p in nonlinear:
                    term = self._term(name)

                    def obj(log_v: float, term: EffectTerm = term, pname: str = p.name) -> float:
                        params[term.name][pname] = float(10.0**log_v)
                        total = 0.0
                        for axis in (0, 1):
                            blocks[axis][term.name] = windowed_design(
                                term,
                                ts,
                                history,
                                scan_sign=sign,
                                params=params[term.name],
                                axis=axis,
                            )
                            x = np.hstack(self._supported(blocks[axis]))
                            total += weighted_rss(x, xy[:, axis], w)
                        return total

                    grid = np.log10(p.grid())
                    step = float(grid[1] - grid[0]) if grid.size > 1 else 0.1
                    local = not first_pass or name in warm
                    if local:
                        # Refine around the current value only.
                        best_log = float(np.log10(params[name][p.name]))
                        best_val = obj(best_log)
                        lo = max(float(grid[0]), best_log - step)
                        hi = min(float(grid[-1]), best_log + step)
                        inside = self._refined(obj, lo, hi, best_log, best_val, grid)
                        if inside or not first_pass:
                            continue
                    values = [obj(g) for g in grid]
                    best = int(np.argmin(values))
                    best_log, best_val = float(grid[best]), float(values[best])
                    lo = grid[max(best - 1, 0)]
                    hi = grid[min(best + 1, grid.size - 1)]
                    self._refined(obj, lo, hi, best_log, best_val, grid)
        self.params = params
        self.active = active
        self.add_intercept = self._needs_intercept(active)
        self.fits = []
        self.columns = []
        residuals = np.zeros_like(xy)
        for axis in (0, 1):
            if searched:
                blocks_a = self.design_blocks(ts, history, sign, axis, active=active, params=params)
                raw = dict(blocks_a)
            else:  # θ as when the terms were chosen: their blocks are built
                raw = {"intercept": np.ones((ts.shape[0], 1))} if self.add_intercept else {}
                raw.update({name: self._built[(name, axis)] for name in active})
            self.columns.append([(name, int(b.shape[1])) for name, b in raw.items()])
            x = np.hstack(list(raw.values()))
            fit = solve_wls(x, xy[:, axis], w)
            weak = self._weak_new_columns(raw, fit)
            if weak.any():
                x = np.where(weak[None, :], 0.0, x)
                fit = solve_wls(x, xy[:, axis], w)
            self.fits.append(fit)
            residuals[:, axis] = xy[:, axis] - x[:, fit.keep] @ fit.coef
        self._fit_residual(t, residuals, history)

    def _inputs(self, active: Sequence[str], history: History) -> tuple[str, ...]:
        """What the search of θ depends on besides the points: each active term
        with its number of supported columns (``name|k``: creep has none before
        the first move), and the number of logged events (``events|n``)."""
        keys = []
        for name in active:
            k = max(int(np.count_nonzero(self._built[(name, a)].any(axis=0))) for a in (0, 1))
            keys.append(f"{name}|{k}")
        keys.append(f"events|{len(history.events)}")
        return tuple(keys)

    def _search_due(self, n: int, inputs: tuple[str, ...]) -> bool:
        """Whether θ is searched at this fit: a term became active or gained a
        supported column, an event was logged, or the points grew by
        :attr:`PhysicsConfig.search_growth` since the last search (every fit
        while there are few points, or with growth 0). A term searched before
        with the same support starts from its θ (a warm start)."""
        growth = self.config.search_growth
        if growth <= 0 or n < _ALWAYS_SEARCH_BELOW or inputs != self._searched_terms:
            return True
        return n >= (1.0 + growth) * self._searched_at

    def _refined(
        self,
        obj: Any,
        lo: float,
        hi: float,
        best_log: float,
        best_val: float,
        grid: FloatArray,
    ) -> bool:
        """Bounded 1-D refinement (Brent, on log θ) of ``obj`` between ``lo``
        and ``hi``, leaving θ at the better of it and ``best_log``. False when
        the optimum lies at a bound that is not the grid's own end: the
        neighbourhood did not hold it, and the caller scans the whole grid."""
        from scipy.optimize import minimize_scalar

        res = minimize_scalar(obj, bounds=(lo, hi), method="bounded", options={"xatol": 0.005})
        x = float(res.x)
        if float(res.fun) <= best_val:
            best_log, best_val = x, float(res.fun)
        obj(best_log)
        edge = 0.02 * (hi - lo)
        at_lo = best_log <= lo + edge and lo > float(grid[0])
        at_hi = best_log >= hi - edge and hi < float(grid[-1])
        return not (at_lo or at_hi)

    def _fit_residual(self, t: FloatArray, residuals: FloatArray, history: History) -> None:
        self.last_residual = residuals[-1].copy()
        n = residuals.shape[0]
        dof = max(n - sum(int(f.keep.sum()) for f in self.fits) // 2, 1)
        self.residual_sd = np.sqrt(np.sum(residuals**2, axis=0) / dof)
        self._residuals = np.array(residuals, dtype=np.float64)
        if self.config.residual == "ar1":
            r = residuals[-50:]
            if r.shape[0] >= 8:
                num = np.sum(r[1:] * r[:-1], axis=0)
                den = np.sum(r[:-1] ** 2, axis=0)
                self.phi = np.clip(np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0), 0, 1)
            else:
                # Too few residuals to estimate φ: stay anchored to the last point.
                self.phi = np.ones(2)
        elif self.config.residual == "nn" and self.residual_net is not None:
            from afmdrift.model._nn import channel_matrix

            self.residual_net.fit(residuals, channel_matrix(history, self.nn_config.channels, t))

    # ---------------------------------------------------------------- predict
    def model_at(
        self,
        t_s: npt.ArrayLike,
        history: History,
        *,
        drift_only: bool = False,
        scan_sign: float | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """Deterministic part (terms only) and its parametric σ at ``t_s``, each (n, 2).

        With ``drift_only`` the terms that describe the measurement rather than
        the sample position (:attr:`EffectTerm.measurement_artefact`, e.g.
        ``scan_direction``) take their value in a frame scanned like the
        session reference, against which positions are measured (there the
        artefact cancels, so that frame shows the drift itself); with the
        reference's direction unknown they are left out. ``scan_sign`` (+1 up,
        −1 down) is the direction of the frame scanned at ``t_s`` where it is
        known; otherwise it is extrapolated from the last frames.
        """
        t = as_times(t_s)
        if scan_sign is None:
            sign = future_scan_sign(t, self.log.t(), np.asarray(self.log.scan_sign))
        else:
            sign = np.full(t.size, float(scan_sign))
        ref_sign = self.log.ref_sign
        mean = np.zeros((t.size, 2))
        var = np.zeros((t.size, 2))
        for axis, fit in enumerate(self.fits):
            blocks = self.design_blocks(t, history, sign, axis)
            widths = dict(self.columns[axis])
            parts = []
            for name, b in blocks:
                block = _conform(b, widths[name])
                if drift_only and name != "intercept" and self._term(name).measurement_artefact:
                    if ref_sign is None:
                        block = np.zeros_like(block)
                    else:
                        as_reference = self._term(name).design(
                            t,
                            history,
                            scan_sign=np.full_like(sign, ref_sign),
                            params=self.params[name],
                            axis=axis,
                        )
                        block = _conform(as_reference, widths[name])
                parts.append(block)
            x = np.hstack(parts)[:, fit.keep]
            mean[:, axis] = x @ fit.coef
            var[:, axis] = np.einsum("ij,jk,ik->i", x, fit.cov, x)
        return mean, np.sqrt(np.maximum(var, 0.0))

    def _residual_at(self, t: FloatArray, history: History) -> FloatArray:
        out = np.zeros((t.size, 2))
        t_last = self.log.t_s[-1]
        step = self.log.step_s()
        h = np.maximum((t - t_last) / step, 0.0) if math.isfinite(step) else np.zeros_like(t)
        ahead = t >= t_last
        if self.config.residual == "ar1":
            out[ahead] = self.phi[None, :] ** h[ahead, None] * self.last_residual[None, :]
        elif self.config.residual == "nn" and self.residual_net is not None:
            from afmdrift.model._nn import channel_matrix

            lags = self.nn_config.lags
            r = np.asarray(self._residuals[-lags - 1 :], dtype=np.float64).reshape(-1, 2)
            tail = self.log.t()[-r.shape[0] :]
            inc = self.residual_net.next_increment(
                r, channel_matrix(history, self.nn_config.channels, tail)
            )
            if inc is not None:
                out[ahead] = self.last_residual[None, :] + h[ahead, None] * inc[None, :]
        return out

    def predict(self, t_s: npt.ArrayLike, history: History) -> Prediction:
        return self._predict(t_s, history, drift_only=False)

    def predict_scanned(
        self, t_s: npt.ArrayLike, direction: ScanDirection, history: History
    ) -> Prediction:
        """:meth:`predict` in the frame's own scan direction, not one
        extrapolated from the frames before it."""
        sign = 1.0 if direction is ScanDirection.UP else -1.0
        return self._predict(t_s, history, drift_only=False, scan_sign=sign)

    def predict_drift(self, t_s: npt.ArrayLike, history: History) -> Prediction:
        """The sample position, without the scan-direction bias of the measurements."""
        return self._predict(t_s, history, drift_only=True)

    def _predict(
        self,
        t_s: npt.ArrayLike,
        history: History,
        *,
        drift_only: bool,
        scan_sign: float | None = None,
    ) -> Prediction:
        self._require_data()
        t = as_times(t_s)
        if not self.fits:
            xy = self.log.xy()
            return Prediction(t, np.repeat(xy[-1:], t.size, axis=0), np.ones((t.size, 2)))
        mean, sd = self.model_at(t, history, drift_only=drift_only, scan_sign=scan_sign)
        mean = mean + self._residual_at(t, history)
        res_sd = np.where(np.isfinite(self.residual_sd), self.residual_sd, 0.0)
        sigma = np.sqrt(sd**2 + res_sd[None, :] ** 2)
        return Prediction(t, mean, sigma)

    # ------------------------------------------------------------------ state
    def offset_play(self) -> OffsetPlay | None:
        """The fitted ``hysteresis`` play: half-width r and, per axis, the gain
        −h/r by which the measured position follows the play gap (clipped to
        [−1, 1.5]; 0 where h is within 2σ of zero)."""
        if "hysteresis" not in self.active or not self.fits:
            return None
        r = float(self.params["hysteresis"]["play_nm"])
        gain = [0.0, 0.0]
        for axis, fit in enumerate(self.fits):
            start = 0
            for name, k in self.columns[axis]:
                if name == "hysteresis":
                    break
                start += k
            else:
                continue
            if not fit.keep[start]:
                continue
            j = int(np.count_nonzero(fit.keep[:start]))
            h, var = float(fit.coef[j]), float(fit.cov[j, j])
            if math.isfinite(h) and h * h > 4.0 * max(var, 0.0):
                gain[axis] = min(max(-h / r, -1.0), 1.5)
        if gain == [0.0, 0.0]:
            return None
        return OffsetPlay(play_nm=r, gain=(gain[0], gain[1]))

    def coefficients(self) -> dict[str, dict[str, list[float]]]:
        """Fitted linear coefficients per active term and axis (x, y), for reports.

        Columns dropped as all-zero (e.g. creep before any move) read NaN.
        """
        out: dict[str, dict[str, list[float]]] = {}
        for axis, fit in enumerate(self.fits):
            full = np.full(fit.keep.size, math.nan)
            full[fit.keep] = fit.coef
            i = 0
            for name, k in self.columns[axis]:
                out.setdefault(name, {})["xy"[axis]] = [float(v) for v in full[i : i + k]]
                i += k
        return out

    def state_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "config": self.config.model_dump(),
            "nn_config": self.nn_config.model_dump(),
            "log": self.log.to_dict(),
            "params": self.params,
            "active": list(self.active),
            "fits": [
                {
                    "coef": f.coef.tolist(),
                    "cov": f.cov.tolist(),
                    "keep": f.keep.tolist(),
                    "wrss": f.wrss,
                }
                for f in self.fits
            ],
            "columns": [[[n, k] for n, k in axis_cols] for axis_cols in self.columns],
            "phi": self.phi.tolist(),
            "last_residual": self.last_residual.tolist(),
            "residual_sd": [None if not math.isfinite(v) else float(v) for v in self.residual_sd],
            "residuals": [[float(a), float(b)] for a, b in self._residuals],
            "residual_net": None if self.residual_net is None else self.residual_net.state_dict(),
            "searched_at": self._searched_at,
            "searched_terms": list(self._searched_terms),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        type(self).__init__(
            self,
            PhysicsConfig.model_validate(state["config"]),
            nn_config=NNConfig.model_validate(state["nn_config"]),
        )
        self.log = ObservationLog.from_dict(state["log"])
        self.params = {
            k: {kk: float(vv) for kk, vv in v.items()} for k, v in state["params"].items()
        }
        self.active = list(state["active"])
        self.add_intercept = self._needs_intercept(self.active)
        self.fits = [
            FitResult(
                np.asarray(f["coef"], dtype=np.float64),
                np.asarray(f["cov"], dtype=np.float64).reshape(len(f["coef"]), len(f["coef"])),
                np.asarray(f["keep"], dtype=bool),
                float(f["wrss"]),
            )
            for f in state["fits"]
        ]
        self.columns = [[(str(n), int(k)) for n, k in ac] for ac in state["columns"]]
        self.phi = np.asarray(state["phi"], dtype=np.float64)
        self.last_residual = np.asarray(state["last_residual"], dtype=np.float64)
        self.residual_sd = np.array(
            [math.nan if v is None else float(v) for v in state["residual_sd"]]
        )
        self._residuals = np.asarray(state["residuals"], dtype=np.float64).reshape(-1, 2)
        # A state written before the search schedule: θ is searched at the next fit.
        self._searched_at = int(state.get("searched_at", 0))
        self._searched_terms = tuple(str(n) for n in state.get("searched_terms", ()))
        if self.residual_net is not None and state["residual_net"] is not None:
            self.residual_net.load_state_dict(state["residual_net"])


class PhysicsNNPredictor(PhysicsPredictor):
    """:class:`PhysicsPredictor` with the paper's NN learning the residual."""

    name = "physics_nn"

    def __init__(
        self, config: PhysicsConfig | None = None, *, nn_config: NNConfig | None = None
    ) -> None:
        cfg = (config or PhysicsConfig()).model_copy(update={"residual": "nn"})
        super().__init__(cfg, nn_config=nn_config)
