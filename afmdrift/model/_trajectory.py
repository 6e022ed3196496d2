"""The drift trajectory p(t), from block rows placed at their scan times.

A frame's rows are scanned one after another (a 512-line frame at 4 Hz takes
128 s), so each block row of a registration is its own sample of the drift:
the block vectors of block row j measure

    v_j = p(t_cur,j) − p(t_ref,j) + (s_cur − s_ref)·b/2 − (O(t_cur,j) − O(t_ref,j))

where t_cur,j is the scan time of the row's content in the current frame,
t_ref,j its scan time in the reference frame (the keyframe it was measured
against), O the commanded offset (``afmdrift.model._positions``), b the
scan-direction bias and s = +1 for an up frame, −1 for a down frame. A
512² frame with 64 px blocks gives 8 such samples, not one.

Estimator
---------
p(t) is represented by its values at *knots*: the block-row scan times of
every accepted frame (linear in between, and within a frame linear beyond
its first and last knot). It is the penalised least-squares (MAP) estimate
under

* the block-row constraints above, each with the standard uncertainty of its
  row mean (the frame's residual block spread, :mod:`afmdrift.registration._trend`,
  divided by the root of the row's effective block count);
* an integrated random-walk prior on p: consecutive knots' second divided
  differences ``(p_c − p_b)/h₂ − (p_b − p_a)/h₁`` are N(0, q·(h₁ + h₂)/2),
  the discrete form of the prior whose MAP estimate is a cubic smoothing
  spline (Wahba, J. R. Stat. Soc. B 40, 364 (1978); the same model as a
  constant-velocity Kalman filter with RTS smoothing). ``q`` (nm²/s³, the
  velocity diffusion) is ``ModelConfig.trajectory_q``, by default
  :func:`default_q` of the first frame's scan time;
* the scan-direction bias b as one extra unknown (prior N(0, (10 nm)²)):
  it jumps between up and down frames, which the smooth curve cannot, so it
  does not bend p; positions are reported *with* the frame's bias relative to
  the session reference, as the registration sees them, so the ``scan_direction``
  model term keeps seeing it;
* the gauge p(t_ref) = 0 at the session reference's mid-scan time.

A new reference whose position is not measured (:meth:`DriftTrajectory.add_reference`)
starts a new *chain*: its mid-scan p is the causal estimate continued from
the frames before it (the smoothness prior), and is then held there by a
gauge of its own, so the frames measured against it (and against the later
keyframes of its chain) never re-estimate it: their p is the reference's plus
their measured displacement from it. Each position's σ is the root-sum-square
of its chain reference's σ (0 for the session reference; a resumed anchor's
stored σ) and of its displacement's σ.

The constraints link frames as far apart as a keyframe and its later frames,
so this also ties the chain of frames together ("frame-to-frame links").

Two modes
---------
causal (the daemon, and everything that reports what the daemon can do)
    Each new frame updates the information form (normal equations) of the
    free knots with its rows and is solved at once (Cholesky); knots of
    frames that no later frame can refer to (older than the newest
    ``window`` frames and not the keyframe of the newest one) are then
    marginalised out by a Schur complement, not frozen, so the estimate of
    the newest frame is that of solving every frame so far at once: the
    Kalman filter of this model, at a cost that does not grow with the
    session (each update's rows, the dense algebra over some 40 unknowns and
    the marginalisation are a few compiled calls,
    :mod:`afmdrift.model._trajectory_kernels`). It uses
    only what has arrived. Uncertainties are scaled by the
    running χ² per degree of freedom of the block-row constraints when that
    exceeds 1.
smoothed (``afmdrift correct``, the smoothed trajectory of ``afmdrift replay``)
    All knots of the session solved at once (sparse normal equations).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from afmdrift.model._trajectory_kernels import (
    FREE_KNOT_SIGMA_NM,
    MIN_SIGMA_NM,
    compile_kernels,
    constraint_rows,
    extend_and_solve,
    knot_weights,
    schur,
    smoothness_rows,
)

__all__ = ["BandConstraint", "DriftTrajectory", "FrameTrajectory", "default_q"]

FloatArray = npt.NDArray[np.float64]

#: Velocity diffusion of the prior for frames scanned in REFERENCE_SCAN_S, nm²/s³
#: (see :func:`default_q`).
REFERENCE_Q_NM2_S3 = 1e-5
#: Scan time at which REFERENCE_Q_NM2_S3 applies (512 lines at 4 Hz), s.
REFERENCE_SCAN_S = 128.0


def default_q(scan_s: float) -> float:
    """The prior's velocity diffusion for frames scanned in ``scan_s`` seconds.

    1e-5 nm²/s³ for 128 s scans and ∝ 1/scan_s² otherwise (0.16 nm²/s³ for
    the 1 s frames of a high-speed AFM movie). Chosen by replaying simulator
    sessions (graphite-paper, gold-manipulation-8h, hidden creep and warm-up,
    default, quiet-lab-24h) at 1e-4, 3e-5 and 1e-5: the stiffer prior pins
    down the shape of each frame's own scan, which the constraints (all
    differences between frames) leave free, so the keyframe chain wanders
    less (graphite-paper seed 3: 0.77 → 0.37 nm RMS of ``trajectory.csv``),
    and it still follows a warm-up and creep after offset moves within each
    frame (increments unchanged or better on every session tried). An
    instrument whose drift changes faster sets ``[model] trajectory_q``.
    """
    if not (math.isfinite(scan_s) and scan_s > 0):
        return REFERENCE_Q_NM2_S3
    return REFERENCE_Q_NM2_S3 * (REFERENCE_SCAN_S / scan_s) ** 2


#: Prior standard deviation of the scan-direction bias b, nm.
BIAS_PRIOR_NM = 10.0
#: Standard deviation of the gauge constraint p(t_ref) = 0, nm.
GAUGE_SIGMA_NM = 1e-3
#: The known part of a row whose knots are all free (shared: never written).
_ZERO2 = np.zeros(2)
_ZERO2.setflags(write=False)
#: The columns of a frame whose knots are not free (shared: never written).
_NO_COLS = np.zeros(0, dtype=np.intp)
_NO_COLS.setflags(write=False)


@dataclass(frozen=True, slots=True)
class BandConstraint:
    """One block row's measurement against its reference frame.

    ``value_nm`` is the row's mean block vector plus the commanded offset
    change ``O(t_s) − O(t_ref_s)``, i.e. p(t_s) − p(t_ref_s) + bias terms.
    """

    ref_key: int
    t_s: float
    t_ref_s: float
    value_nm: tuple[float, float]
    sigma_nm: float


@dataclass(slots=True)
class _Frame:
    key: int
    t_s: FloatArray  # knot times, increasing
    sign: int  # +1 up, -1 down
    t_mid_s: float
    constraints: list[BandConstraint]
    p: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))  # bias-free p at knots
    sigma: FloatArray = field(default_factory=lambda: np.zeros(0))
    fixed: bool = False
    anchor: bool = False  # known, not measured: never re-solved
    #: The key of the frame that started the frame's chain (see add_reference).
    chain: int = -1
    #: A chain reference's reported mid-scan p, held there (None otherwise).
    gauge_nm: FloatArray | None = None


@dataclass(frozen=True, slots=True)
class FrameTrajectory:
    """A frame's drift samples, as the registration sees them (bias included).

    ``t_s`` (k,) knot times, ``xy_nm`` (k, 2), ``sigma_nm`` (k, 2); ``mid_nm``
    and ``mid_sigma_nm`` the same at the frame's mid-scan time. The
    uncertainties are those of the reported values p + ds·b (a down frame's
    p alone is known only up to the bias b; p + ds·b is what its block rows
    determine). In causal mode they are the frame's when it was added.
    """

    key: int
    t_s: FloatArray
    xy_nm: FloatArray
    sigma_nm: FloatArray
    mid_nm: FloatArray
    mid_sigma_nm: float


class DriftTrajectory:
    """Causal and smoothed estimates of p(t) from block-row constraints.

    Parameters
    ----------
    q_nm2_s3 : float
        Velocity diffusion of the integrated random-walk prior, nm²/s³.
    window : int
        Frames solved jointly in causal mode (the newest ones).
    keep_history : bool
        Keep every frame for :meth:`smoothed`; otherwise frames are forgotten
        once marginalised (bounded memory for a long-running daemon).
    """

    def __init__(self, *, q_nm2_s3: float, window: int = 4, keep_history: bool = True) -> None:
        if not (math.isfinite(q_nm2_s3) and q_nm2_s3 > 0):
            raise ValueError(f"q_nm2_s3 must be finite and > 0, got {q_nm2_s3!r}")
        if window < 2:
            raise ValueError(f"window must be >= 2 frames, got {window!r}")
        compile_kernels()
        self.q = float(q_nm2_s3)
        self.window = int(window)
        self.keep_history = keep_history
        self.frames: dict[int, _Frame] = {}
        self.order: list[int] = []  # keys by time
        self.origin: tuple[int, float] | None = None  # (key, t) where p = 0
        self.bias = np.zeros(2)
        self.bias_var = BIAS_PRIOR_NM**2
        self.breaks: list[float] = []
        #: σ² of each chain's reference position, by the chain's key.
        self.chain_var: dict[int, float] = {}
        # Causal state: information form over the free unknowns (index 0 is
        # the bias), their indices, and the last two knots in time.
        self._h = np.array([[1.0 / BIAS_PRIOR_NM**2]])
        self._g = np.zeros((1, 2))
        self._cols: dict[int, npt.NDArray[np.intp]] = {}  # a free frame's knot columns
        self._tail: list[tuple[float, tuple[int, int]]] = []
        self._chi2 = 0.0
        self._chi2_n = 0

    def __len__(self) -> int:
        return len(self.order)

    def add_break(self, t_s: float) -> None:
        """Let p jump at ``t_s`` (a logged tip change shifts the image at once):
        no smoothness row spans it, so the knots after it follow their own
        constraints rather than being bent towards the curve before it."""
        if math.isfinite(t_s):
            bisect.insort(self.breaks, float(t_s))

    def _breaks_between(self, t0: float, t1: float) -> bool:
        """A break in (t0, t1]."""
        k = bisect.bisect_right(self.breaks, t0)
        return k < len(self.breaks) and self.breaks[k] <= t1

    def add_frame(
        self,
        key: int,
        knot_times_s: npt.ArrayLike,
        *,
        sign: int,
        t_mid_s: float,
        constraints: list[BandConstraint],
    ) -> FrameTrajectory:
        """Add a frame (its knots and its constraints, which may only refer
        to frames already added) and return its causal estimate."""
        t = np.sort(np.asarray(knot_times_s, dtype=np.float64).reshape(-1))
        if t.size == 0 or not np.isfinite(t).all():
            raise ValueError(f"frame {key}: knot times must be finite, got {t!r}")
        if self.order and t[0] <= self.frames[self.order[-1]].t_s[-1]:
            raise ValueError(f"frame {key}: its knots start before the previous frame's end")
        for c in constraints:
            if c.ref_key not in self.frames:
                raise ValueError(
                    f"frame {key}: reference frame {c.ref_key} is not in the trajectory"
                )
        frame = _Frame(
            key=key,
            t_s=t,
            sign=1 if sign >= 0 else -1,
            t_mid_s=t_mid_s,
            constraints=list(constraints),
        )
        frame.p = np.zeros((t.size, 2))
        frame.sigma = np.zeros(t.size)
        if self.origin is None:
            self.origin = (key, float(t_mid_s))
            self.chain_var[key] = 0.0
        frame.chain = self._chain_of(key, constraints)
        self.frames[key] = frame
        self.order.append(key)
        self._filter_add(frame)
        return self.estimate(key)

    def _chain_of(self, key: int, constraints: list[BandConstraint]) -> int:
        """The chain a new frame belongs to: its references' (one chain: a
        frame is measured against one tracker's frames), else the latest
        frame's, else its own."""
        if constraints:
            return self.frames[constraints[0].ref_key].chain
        if self.order:
            return self.frames[self.order[-1]].chain
        return key

    def add_reference(
        self, key: int, knot_times_s: npt.ArrayLike, *, sign: int, t_mid_s: float
    ) -> FrameTrajectory:
        """Add a new reference whose position is not measured: it starts a new
        chain (see the module docstring) and returns its estimate.

        Its mid-scan p is the causal trajectory continued to it (the frames
        before it and the smoothness prior) with that estimate's σ, and is held
        there: later frames measure their displacement from it but do not move
        it. Positions of its chain carry its σ in root-sum-square.
        """
        if not self.order:
            return self.add_frame(key, knot_times_s, sign=sign, t_mid_s=t_mid_s, constraints=[])
        est = self.add_frame(key, knot_times_s, sign=sign, t_mid_s=t_mid_s, constraints=[])
        frame = self.frames[key]
        frame.chain = key
        frame.gauge_nm = est.mid_nm.copy()
        self.chain_var[key] = est.mid_sigma_nm**2
        cols = self._cols.get(key)
        if cols is not None:
            # The gauge p + ds·b = the estimate at mid-scan, into the
            # information form: the solution already satisfies it (it is
            # that solution), so only the uncertainties it leaves change.
            row = np.zeros(self._h.shape[0])
            i, j, wi, wj = knot_weights(frame.t_s, frame.t_mid_s)
            row[cols[i]] += wi
            if wj != 0.0:
                row[cols[j]] += wj
            row[0] += self._bias_shift(frame)
            row /= GAUGE_SIGMA_NM
            self._h += np.outer(row, row)
            self._g += np.outer(row, est.mid_nm / GAUGE_SIGMA_NM)
        return est

    # ------------------------------------------------------------------ causal

    def _filter_add(self, frame: _Frame) -> None:
        """Causal update: the frame's knots join the information form (H, g)
        of the free knots, its rows are added, the system is solved, and the
        frames no longer needed are marginalised out (Schur complement), so
        the estimate equals that of solving all frames so far at once."""
        n_new = frame.t_s.size
        base = self._h.shape[0]
        # The weak prior of each new knot is centred on the latest estimate.
        centre = np.zeros(2)
        if self._tail:
            k_last, i_last = self._tail[-1][1]
            centre = self.frames[k_last].p[i_last]
        new_cols = np.arange(base, base + n_new)
        self._cols[frame.key] = new_cols
        # smoothness over the last two knots before the frame, then its own
        previous = self._tail[-2:]
        chain = previous + [(float(frame.t_s[i]), (frame.key, i)) for i in range(n_new)]
        self._tail = chain[-2:]
        cons = frame.constraints
        gauge = self.origin is not None and self.origin[0] == frame.key
        n_chain = len(chain)
        a = np.zeros((max(0, n_chain - 2) + len(cons) + int(gauge), base + n_new))
        y = np.zeros((a.shape[0], 2))
        # smoothness (the previous knots may be known: marginalised or anchored)
        t_chain = np.concatenate([[node[0] for node in previous], frame.t_s])
        col_chain = np.concatenate(
            [np.array([self._free_col(*node[1]) for node in previous], dtype=np.intp), new_cols]
        )
        known = np.zeros((n_chain, 2))
        for q, (_, (k, i)) in enumerate(previous):
            if col_chain[q] < 0:
                known[q] = self.frames[k].p[i]
        breaks = np.asarray(self.breaks, dtype=np.float64)
        first_data = smoothness_rows(a, y, t_chain, col_chain, known, breaks, self.q)
        # the frame's block-row constraints, by reference frame
        used = first_data
        if cons:
            t_cur = np.array([c.t_s for c in cons])
            t_ref = np.array([c.t_ref_s for c in cons])
            values = np.array([c.value_nm for c in cons], dtype=np.float64).reshape(-1, 2)
            sigma = np.array([c.sigma_nm for c in cons], dtype=np.float64)
            keys = np.array([c.ref_key for c in cons])
            for ref_key in dict.fromkeys(keys.tolist()):
                sel = keys == ref_key
                ref = self.frames[ref_key]
                ref_cols = self._cols.get(ref_key, _NO_COLS)
                t_c = t_cur[sel]
                constraint_rows(
                    a, y, used, frame.t_s, new_cols, t_c, ref.t_s, ref_cols, ref.p,
                    t_ref[sel], values[sel], sigma[sel], 0.5 * (frame.sign - ref.sign),
                )  # fmt: skip
                used += t_c.size
        n_data = used - first_data
        if gauge:
            # p = 0 at the session reference's mid-scan time (its knots are free)
            assert self.origin is not None
            i, j, wi, wj = knot_weights(frame.t_s, self.origin[1])
            a[used, new_cols[i]] += wi / GAUGE_SIGMA_NM
            if wj != 0.0:
                a[used, new_cols[j]] += wj / GAUGE_SIGMA_NM
            used += 1
        a, y = a[:used], y[:used]
        # Solve, and the variances of what is reported: the bias, and this
        # frame's knots *with* the frame's bias shift ds·b (a down frame's p
        # alone is only known up to b; p + ds·b is what the data determine).
        # Older frames keep the uncertainty they were reported with.
        shift = self._bias_shift(frame)
        self._h, self._g, sol, var, ok = extend_and_solve(
            self._h, self._g, n_new, centre, a, y, shift
        )
        if not ok:
            # Numerically not positive definite (constraints far stronger than
            # the priors): the symmetric eigen-solution, which always exists.
            n = self._h.shape[0]
            report = np.zeros((n, n_new + 1))
            report[0, 0] = 1.0
            report[new_cols, np.arange(1, n_new + 1)] = 1.0
            report[0, 1:] = shift
            w, v = np.linalg.eigh(self._h)
            inv = (v / np.maximum(w, w.max() * 1e-15)) @ v.T
            sol = inv @ self._g
            var = np.sum(report * (inv @ report), axis=0)
        if n_data:
            r = a[first_data : first_data + n_data] @ sol - y[first_data : first_data + n_data]
            self._chi2 += float(np.vdot(r, r))
            self._chi2_n += 2 * n_data
        scale = max(1.0, self._chi2 / self._chi2_n) if self._chi2_n else 1.0
        for k, cols in self._cols.items():
            self.frames[k].p[:] = sol[cols]
        chain_var = self.chain_var.get(frame.chain, 0.0)
        frame.sigma[:] = np.sqrt(np.maximum(var[1:], 0.0) * scale + chain_var)
        self.bias = np.asarray(sol[0], dtype=np.float64)
        self.bias_var = max(float(var[0]) * scale, 1e-12)
        # marginalise what no future frame can refer to
        recent = set(self.order[-self.window :])
        keep = recent | {c.ref_key for c in frame.constraints}
        gone = [k for k in self._cols if k not in keep]
        if gone:
            self._marginalise(gone)

    def _terms_at(
        self,
        key: int,
        t: float,
        scale: float,
        index: dict[tuple[int, int], int],
    ) -> tuple[list[tuple[int, float]], FloatArray]:
        """Terms of scale·p(t) in frame ``key``'s knots: knots in ``index``
        as terms, the others (fixed or anchored) as constants."""
        f = self.frames[key]
        i, j, wi, wj = knot_weights(f.t_s, t)
        terms: list[tuple[int, float]] = []
        const = _ZERO2  # shared, never written: most knots are free
        for idx, w in ((i, wi), (j, wj)):
            if w == 0.0:
                continue
            c = index.get((key, idx))
            if c is None:
                const = const + scale * w * f.p[idx]
            else:
                terms.append((c, scale * w))
        return terms, const

    def _free_col(self, key: int, i: int) -> int:
        """Column of knot ``i`` of frame ``key`` in the causal state, −1 if
        it is not free (marginalised or anchored)."""
        cols = self._cols.get(key)
        return -1 if cols is None else int(cols[i])

    def _marginalise(self, gone_keys: list[int]) -> None:
        """Marginalise the knots of frames ``gone_keys`` out (Schur complement)."""
        n = self._h.shape[0]
        drop = np.concatenate([self._cols.pop(k) for k in gone_keys])
        mask = np.ones(n, dtype=bool)
        mask[drop] = False
        keep = np.nonzero(mask)[0]
        h, g, ok = schur(self._h, self._g, keep, drop)
        if not ok:  # not numerically positive definite: the general solver
            h_k = self._h.take(keep, axis=0)
            h_kd = h_k.take(drop, axis=1)
            rhs = np.column_stack([h_kd.T, self._g[drop]])
            x = np.linalg.solve(self._h.take(drop, axis=0).take(drop, axis=1), rhs)
            h = h_k.take(keep, axis=1) - h_kd @ x[:, : keep.size]
            g = self._g[keep] - h_kd @ x[:, keep.size :]
        self._h, self._g = h, g
        remap = np.full(n, -1)
        remap[keep] = np.arange(keep.size)
        self._cols = {k: remap[c] for k, c in self._cols.items()}
        for key in gone_keys:
            self.frames[key].fixed = True
        if not self.keep_history:
            # Marginalised frames are not needed again (the origin's
            # direction is); only the smoothed estimate would read them.
            forget = {k for k in gone_keys if self.origin is None or k != self.origin[0]}
            for key in forget:
                del self.frames[key]
            self.order = [k for k in self.order if k not in forget]
            chains = {f.chain for f in self.frames.values()}
            self.chain_var = {c: v for c, v in self.chain_var.items() if c in chains}

    def add_anchor(
        self,
        key: int,
        knot_times_s: npt.ArrayLike,
        *,
        sign: int,
        t_mid_s: float,
        p_nm: npt.ArrayLike,
        sigma_nm: float,
    ) -> None:
        """Add a frame whose drift is known, not measured (a resumed service's
        stored reference): its knots are fixed at ``p_nm`` (2,) with
        ``sigma_nm``. It starts a chain: the positions measured from it carry
        ``sigma_nm`` in root-sum-square."""
        t = np.sort(np.asarray(knot_times_s, dtype=np.float64).reshape(-1))
        frame = _Frame(
            key=key,
            t_s=t,
            sign=1 if sign >= 0 else -1,
            t_mid_s=t_mid_s,
            constraints=[],
            fixed=True,
            anchor=True,
            chain=key,
        )
        self.chain_var[key] = float(sigma_nm) ** 2
        frame.p = np.tile(np.asarray(p_nm, dtype=np.float64).reshape(1, 2), (t.size, 1))
        frame.sigma = np.full(t.size, float(sigma_nm))
        self._tail = [(float(t[i]), (key, i)) for i in range(t.size)][-2:]
        if self.origin is None:
            self.origin = (key, float(t_mid_s))
        self.frames[key] = frame
        self.order.append(key)

    def smoothed(self) -> dict[int, FrameTrajectory]:
        """All frames solved at once; returns every frame's estimate (the
        causal state is left as it was).

        Raises
        ------
        ValueError
            The trajectory was made with ``keep_history=False``.
        """
        if not self.keep_history:
            raise ValueError("a trajectory made with keep_history=False has no smoothed estimate")
        saved = {k: (f.p.copy(), f.sigma.copy(), f.fixed) for k, f in self.frames.items()}
        bias, bias_var = self.bias.copy(), self.bias_var
        try:
            for f in self.frames.values():
                f.fixed = f.anchor
            self.bias, self.bias_var = np.zeros(2), BIAS_PRIOR_NM**2
            self._solve([k for k in self.order if not self.frames[k].anchor])
            return {k: self.estimate(k) for k in self.order}
        finally:
            for k, (p, s, fx) in saved.items():
                f = self.frames[k]
                f.p, f.sigma, f.fixed = p, s, fx
            self.bias, self.bias_var = bias, bias_var

    @property
    def origin_sign(self) -> int | None:
        """Scan direction of the session reference (+1 up, −1 down; None before one)."""
        return self.frames[self.origin[0]].sign if self.origin else None

    def _bias_shift(self, f: _Frame) -> float:
        """ds of frame ``f``: its positions are reported as p + ds·b, relative
        to the session reference's direction."""
        ref_sign = self.origin_sign
        return 0.5 * (f.sign - (f.sign if ref_sign is None else ref_sign))

    def estimate(self, key: int) -> FrameTrajectory:
        """The current estimate of frame ``key`` (bias of its direction included)."""
        f = self.frames[key]
        shift = self._bias_shift(f) * self.bias
        xy = f.p + shift
        sig = np.empty((f.sigma.size, 2))
        sig[:, 0] = sig[:, 1] = f.sigma
        i, j, wi, wj = knot_weights(f.t_s, f.t_mid_s)
        mid = wi * f.p[i] + wj * f.p[j] + shift
        mid_sigma = float(wi * f.sigma[i] + wj * f.sigma[j])
        return FrameTrajectory(
            key=key, t_s=f.t_s.copy(), xy_nm=xy, sigma_nm=sig, mid_nm=mid, mid_sigma_nm=mid_sigma
        )

    # ------------------------------------------------------------------ solve

    def _solve(self, active: list[int]) -> None:
        col: dict[tuple[int, int], int] = {}
        for k in active:
            for i in range(self.frames[k].t_s.size):
                col[(k, i)] = len(col)
        n = len(col) + 1  # + the bias
        b_col = n - 1
        rows: list[int] = []
        cols: list[int] = []
        vals: list[float] = []
        rhs: list[FloatArray] = []
        wts: list[float] = []

        def add_row(terms: list[tuple[int, float]], value: FloatArray, sigma: float) -> None:
            r = len(rhs)
            for c, a in terms:
                rows.append(r)
                cols.append(c)
                vals.append(a)
            rhs.append(value)
            wts.append(1.0 / sigma)

        # A very weak prior on each free knot keeps a frame without
        # constraints (a new reference) solvable; it never competes with data.
        for (k, i), column in col.items():
            add_row([(column, 1.0)], self.frames[k].p[i].copy(), FREE_KNOT_SIGMA_NM)
        for k in active:
            f = self.frames[k]
            for con in f.constraints:
                t1, c1 = self._terms_at(k, con.t_s, 1.0, col)
                t2, c2 = self._terms_at(con.ref_key, con.t_ref_s, -1.0, col)
                ds = 0.5 * (f.sign - self.frames[con.ref_key].sign)
                terms = t1 + t2
                if ds != 0.0:
                    terms.append((b_col, ds))
                value = np.asarray(con.value_nm, dtype=np.float64) - c1 - c2
                add_row(terms, value, max(con.sigma_nm, MIN_SIGMA_NM))
        # Smoothness over the sorted knots of the active frames, with up to two
        # fixed knots before them.
        seq: list[tuple[float, int | None, FloatArray]] = []
        first = self.order.index(active[0]) if active else len(self.order)
        for k in self.order[max(0, first - 2) :]:
            f = self.frames[k]
            for i in range(f.t_s.size):
                seq.append((float(f.t_s[i]), col.get((k, i)), f.p[i]))
        while len(seq) > 2 and seq[0][1] is None and seq[2][1] is None:
            seq.pop(0)
        for na, nb, nc in zip(seq, seq[1:], seq[2:], strict=False):
            h1, h2 = nb[0] - na[0], nc[0] - nb[0]
            if h1 <= 0 or h2 <= 0 or self._breaks_between(na[0], nc[0]):
                continue
            coef = ((na, 1.0 / h1), (nb, -1.0 / h1 - 1.0 / h2), (nc, 1.0 / h2))
            terms = []
            const = np.zeros(2)
            for node, w in coef:
                if node[1] is None:
                    const += w * node[2]
                else:
                    terms.append((node[1], w))
            if terms:
                add_row(terms, -const, math.sqrt(self.q * 0.5 * (h1 + h2)))
        # Gauges (the session reference's, and each chain reference's), and
        # the bias prior.
        if self.origin is not None and self.origin[0] in active:
            terms, const = self._terms_at(self.origin[0], self.origin[1], 1.0, col)
            add_row(terms, -const, GAUGE_SIGMA_NM)
        for k in active:
            f = self.frames[k]
            if f.gauge_nm is not None:
                terms, const = self._terms_at(k, f.t_mid_s, 1.0, col)
                ds = self._bias_shift(f)
                if ds != 0.0:
                    terms.append((b_col, ds))
                add_row(terms, f.gauge_nm - const, GAUGE_SIGMA_NM)
        add_row([(b_col, 1.0)], self.bias, math.sqrt(self.bias_var))
        m = len(rhs)
        row_w = np.asarray(wts)
        a_mat = sp.csr_matrix((vals, (rows, cols)), shape=(m, n))
        aw = sp.diags(row_w) @ a_mat
        y = np.vstack(rhs) * row_w[:, None]
        normal = (aw.T @ aw).tocsc()
        rhs_n = aw.T @ y
        e_bias = np.zeros(n)
        e_bias[b_col] = 1.0
        if n <= 400:
            dense = normal.toarray()
            sol = np.linalg.solve(dense, rhs_n)
            inv = np.linalg.inv(dense)
            cov_diag, cov_bias = np.diag(inv), inv[:, b_col]
        else:
            lu = spla.splu(normal)
            sol = lu.solve(np.asarray(rhs_n))
            cov_diag = self._diag_of_inverse(lu, n)
            cov_bias = lu.solve(e_bias)
        resid = aw @ sol - y
        dof = max(1, m - n)
        scale = max(1.0, float(np.sum(resid**2)) / (2 * dof))
        for (k, i), c in col.items():
            f = self.frames[k]
            f.p[i] = sol[c]
            # the variance of the reported p + ds·b (see _filter_add), and
            # that of its chain's reference position
            ds = self._bias_shift(f)
            v = cov_diag[c] + ds * ds * cov_diag[b_col] + 2.0 * ds * cov_bias[c]
            f.sigma[i] = math.sqrt(max(0.0, float(v) * scale) + self.chain_var.get(f.chain, 0.0))
        var = cov_diag * scale
        self.bias = np.asarray(sol[b_col], dtype=np.float64)
        self.bias_var = max(float(var[b_col]), 1e-12)

    @staticmethod
    def _diag_of_inverse(lu: spla.SuperLU, n: int) -> FloatArray:
        """Diagonal of the inverse normal matrix (column by column, in blocks)."""
        out = np.empty(n)
        step = 256
        for start in range(0, n, step):
            stop = min(n, start + step)
            e = np.zeros((n, stop - start))
            e[np.arange(start, stop), np.arange(stop - start)] = 1.0
            x = lu.solve(e)
            out[start:stop] = x[np.arange(start, stop), np.arange(stop - start)]
        return out
