"""The compiled kernels of the drift trajectory's causal update.

:class:`~afmdrift.model.DriftTrajectory` keeps the information form of its
free knots (some 40 unknowns) and, for each new frame, adds the frame's rows
(:func:`constraint_rows`, :func:`smoothness_rows`), solves by a dense
Cholesky factorisation (:func:`extend_and_solve`) and marginalises the knots
no later frame can refer to by a Schur complement (:func:`schur`). As
per-term Python lists and NumPy and LAPACK calls these cost more in overhead
than in arithmetic, so they are Numba kernels without the GIL;
:func:`compile_kernels` compiles them once per process. The model they
implement is described in :mod:`afmdrift.model._trajectory`.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

__all__ = [
    "FREE_KNOT_SIGMA_NM",
    "MIN_SIGMA_NM",
    "compile_kernels",
    "constraint_rows",
    "extend_and_solve",
    "knot_weights",
    "schur",
    "smoothness_rows",
]

FloatArray = npt.NDArray[np.float64]

#: Standard deviation of the weak prior on every free knot (centred on the
#: latest estimate), nm: it only keeps a knot without data determined.
FREE_KNOT_SIGMA_NM = 1e3
#: Smallest standard uncertainty of a block-row mean, nm.
MIN_SIGMA_NM = 1e-3


@numba.njit(cache=True, nogil=True)
def _cholesky(h: FloatArray) -> tuple[FloatArray, bool]:
    """Lower Cholesky factor of ``h``; False if it is not numerically
    positive definite."""
    n = h.shape[0]
    c = np.zeros((n, n))
    for j in range(n):
        s = h[j, j]
        for k in range(j):
            s -= c[j, k] * c[j, k]
        if not s > 0.0:
            return c, False
        d = math.sqrt(s)
        c[j, j] = d
        for i in range(j + 1, n):
            s = h[i, j]
            for k in range(j):
                s -= c[i, k] * c[j, k]
            c[i, j] = s / d
    return c, True


@numba.njit(cache=True, nogil=True)
def _forward(c: FloatArray, b: FloatArray) -> FloatArray:
    """``c⁻¹ b`` for a lower triangular ``c``, ``b`` (n, k)."""
    n, m = b.shape
    z = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            s = b[i, j]
            for k in range(i):
                s -= c[i, k] * z[k, j]
            z[i, j] = s / c[i, i]
    return z


@numba.njit(cache=True, nogil=True)
def _backward(c: FloatArray, z: FloatArray) -> FloatArray:
    """``c⁻ᵀ z`` for a lower triangular ``c``, ``z`` (n, k)."""
    n, m = z.shape
    x = np.empty((n, m))
    for i in range(n - 1, -1, -1):
        for j in range(m):
            s = z[i, j]
            for k in range(i + 1, n):
                s -= c[k, i] * x[k, j]
            x[i, j] = s / c[i, i]
    return x


@numba.njit(cache=True, nogil=True)
def extend_and_solve(
    h_old: FloatArray,
    g_old: FloatArray,
    n_new: int,
    centre: FloatArray,
    a: FloatArray,
    y: FloatArray,
    bias_shift: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, bool]:
    """The causal update's dense algebra in one compiled call.

    The information form (H, g) grows by ``n_new`` knots with the weak free
    knot prior centred on ``centre``, takes the weighted rows ``a`` (m, n),
    ``y`` (m, 2) and is solved by Cholesky. Returns ``(h, g, sol, var, ok)``:
    ``var`` holds the variances of the bias and of each new knot shifted by
    ``bias_shift``·b (what is reported); ``ok`` False when H is not
    numerically positive definite (``sol`` and ``var`` are then unset).
    """
    base = h_old.shape[0]
    n = base + n_new
    h = np.zeros((n, n))
    g = np.zeros((n, 2))
    h[:base, :base] = h_old
    g[:base] = g_old
    w = 1.0 / FREE_KNOT_SIGMA_NM**2
    for i in range(base, n):
        h[i, i] += w
        g[i, 0] += centre[0] * w
        g[i, 1] += centre[1] * w
    # aᵀa and aᵀy by loops (a few dozen rows and unknowns: no BLAS call,
    # and far less to compile)
    m = a.shape[0]
    for r in range(m):
        for i in range(n):
            ai = a[r, i]
            if ai == 0.0:
                continue
            g[i, 0] += ai * y[r, 0]
            g[i, 1] += ai * y[r, 1]
            for j in range(n):
                h[i, j] += ai * a[r, j]
    c, ok = _cholesky(h)
    sol = np.zeros((n, 2))
    var = np.zeros(n_new + 1)
    if not ok:
        return h, g, sol, var, False
    sol = _backward(c, _forward(c, g))
    report = np.zeros((n, n_new + 1))
    report[0, 0] = 1.0
    for i in range(n_new):
        report[base + i, 1 + i] = 1.0
        report[0, 1 + i] = bias_shift
    z = _forward(c, report)
    for j in range(n_new + 1):
        s = 0.0
        for i in range(n):
            s += z[i, j] * z[i, j]
        var[j] = s
    return h, g, sol, var, True


@numba.njit(cache=True, nogil=True)
def schur(
    h: FloatArray, g: FloatArray, keep: npt.NDArray[np.intp], drop: npt.NDArray[np.intp]
) -> tuple[FloatArray, FloatArray, bool]:
    """(H, g) with the unknowns ``drop`` marginalised out (Schur complement);
    False if their block is not numerically positive definite."""
    nk, nd = keep.size, drop.size
    h_kk = np.empty((nk, nk))
    h_kd = np.empty((nk, nd))
    h_dd = np.empty((nd, nd))
    rhs = np.empty((nd, nk + 2))
    for i in range(nk):
        for j in range(nk):
            h_kk[i, j] = h[keep[i], keep[j]]
        for j in range(nd):
            h_kd[i, j] = h[keep[i], drop[j]]
    for i in range(nd):
        for j in range(nd):
            h_dd[i, j] = h[drop[i], drop[j]]
        for j in range(nk):
            rhs[i, j] = h_kd[j, i]
        rhs[i, nk] = g[drop[i], 0]
        rhs[i, nk + 1] = g[drop[i], 1]
    c, ok = _cholesky(h_dd)
    if not ok:
        return h, g, False
    x = _backward(c, _forward(c, rhs))
    g_new = np.empty((nk, 2))
    for i in range(nk):
        g_new[i, 0] = g[keep[i], 0]
        g_new[i, 1] = g[keep[i], 1]
        for k in range(nd):
            hk = h_kd[i, k]
            g_new[i, 0] -= hk * x[k, nk]
            g_new[i, 1] -= hk * x[k, nk + 1]
            for j in range(nk):
                h_kk[i, j] -= hk * x[k, j]
    return h_kk, g_new, True


@numba.njit(cache=True, nogil=True)
def knot_weights(knots: FloatArray, t: float) -> tuple[int, int, float, float]:
    """Indices and weights of the linear interpolation (or extrapolation) of
    a frame's knots (times, increasing) at ``t``."""
    n = knots.size
    if n == 1:
        return 0, 0, 1.0, 0.0
    k = min(max(int(np.searchsorted(knots, t)) - 1, 0), n - 2)
    t0, t1 = knots[k], knots[k + 1]
    h = t1 - t0
    w = (t - t0) / h if h > 0 else 0.0
    return k, k + 1, 1.0 - w, w


@numba.njit(cache=True, nogil=True)
def smoothness_rows(
    a: FloatArray,
    y: FloatArray,
    t: FloatArray,
    cols: npt.NDArray[np.intp],
    known: FloatArray,
    breaks: FloatArray,
    q: float,
) -> int:
    """The prior's rows over a chain of knots (times ``t``, increasing;
    columns ``cols``, −1 for a known knot of value ``known``), written from
    row 0 of ``a`` and ``y`` divided by their sigma: for three consecutive
    knots a, b, c not across a break (one in (t_a, t_c]), ``(p_c − p_b)/h₂
    − (p_b − p_a)/h₁ = 0 ± sqrt(q·(h₁ + h₂)/2)``. Returns the row count."""
    r = 0
    for s in range(t.size - 2):
        h1, h2 = t[s + 1] - t[s], t[s + 2] - t[s + 1]
        if h1 <= 0 or h2 <= 0:
            continue
        k = np.searchsorted(breaks, t[s], side="right")
        if k < breaks.size and breaks[k] <= t[s + 2]:
            continue
        sigma = math.sqrt(q * 0.5 * (h1 + h2))
        c0, c1 = 0.0, 0.0
        for d in range(3):
            w = 1.0 / h1 if d == 0 else (-1.0 / h1 - 1.0 / h2 if d == 1 else 1.0 / h2)
            c = cols[s + d]
            if c >= 0:
                a[r, c] += w / sigma
            else:
                c0 += w * known[s + d, 0]
                c1 += w * known[s + d, 1]
        y[r, 0] = -c0 / sigma
        y[r, 1] = -c1 / sigma
        r += 1
    return r


@numba.njit(cache=True, nogil=True)
def constraint_rows(
    a: FloatArray,
    y: FloatArray,
    row0: int,
    knots: FloatArray,
    cols: npt.NDArray[np.intp],
    t_cur: FloatArray,
    ref_knots: FloatArray,
    ref_cols: npt.NDArray[np.intp],
    ref_p: FloatArray,
    t_ref: FloatArray,
    values: FloatArray,
    sigma: FloatArray,
    ds: float,
) -> None:
    """Block-row constraints ``p(t_cur) − p(t_ref) + ds·b = value ± sigma``
    as rows ``row0 ...`` of ``a`` and ``y`` (divided by sigma): the frame's
    knots free (columns ``cols``), the reference's free (``ref_cols``) or,
    when ``ref_cols`` is empty, known (``ref_p``); the bias is column 0."""
    for m in range(t_cur.size):
        r = row0 + m
        s = max(sigma[m], MIN_SIGMA_NM) if not math.isnan(sigma[m]) else sigma[m]
        i, j, wi, wj = knot_weights(knots, t_cur[m])
        if wi != 0.0:
            a[r, cols[i]] += wi / s
        if wj != 0.0:
            a[r, cols[j]] += wj / s
        ri, rj, rwi, rwj = knot_weights(ref_knots, t_ref[m])
        v0, v1 = values[m, 0], values[m, 1]
        if ref_cols.size:
            if rwi != 0.0:
                a[r, ref_cols[ri]] += -rwi / s
            if rwj != 0.0:
                a[r, ref_cols[rj]] += -rwj / s
        else:
            c0, c1 = 0.0, 0.0
            if rwi != 0.0:
                c0 += -rwi * ref_p[ri, 0]
                c1 += -rwi * ref_p[ri, 1]
            if rwj != 0.0:
                c0 += -rwj * ref_p[rj, 0]
                c1 += -rwj * ref_p[rj, 1]
            v0, v1 = v0 - c0, v1 - c1
        if ds != 0.0:
            a[r, 0] += ds / s
        y[r, 0] = v0 / s
        y[r, 1] = v1 / s


_compiled = False


def compile_kernels() -> None:
    """Compile (or load from Numba's disk cache) the causal update's kernels
    once per process, when the first trajectory is made: compiled lazily at
    the first marginalisation instead, they held the GIL for a second or more
    in the middle of a daemon's run (its other tasks waited)."""
    global _compiled
    if _compiled:
        return
    h = np.eye(3)
    g = np.zeros((3, 2))
    extend_and_solve(h, g, 2, np.zeros(2), np.zeros((1, 5)), np.zeros((1, 2)), 0.0)
    schur(np.eye(5), np.zeros((5, 2)), np.arange(3), np.arange(3, 5))
    a, y = np.zeros((3, 5)), np.zeros((3, 2))
    t, cols = np.arange(3.0), np.arange(3)
    knot_weights(t, 1.5)
    smoothness_rows(a, y, t, cols, np.zeros((3, 2)), np.zeros(0), 1.0)
    constraint_rows(
        a, y, 0, t, cols, t, t, cols, np.zeros((3, 2)), t, np.zeros((3, 2)), np.ones(3), 1.0
    )
    _compiled = True
