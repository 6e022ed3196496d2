"""Bounded-memory summary of a long, fast time series: min/max envelope bins.

The offset stream runs at up to 1 kHz for days (86.4 million samples in 24 h),
and a page can draw a few thousand points. :class:`Envelope` keeps the whole
run in at most ``capacity`` bins of equal width: each bin holds the minimum,
maximum and last value of every component, the sample count and how many
samples carried each flag (the offset stream's ``valid: false`` and
``clamped``). When a new sample would need bin ``capacity + 1``, neighbouring
bins are merged pairwise and the width doubles, so memory stays bounded
whatever the run length, and the envelope never hides an excursion: the
extremes of a merged bin are the extremes of its parts (the M4 idea of
Jugel et al., *M4: a visualization-oriented time series data aggregation*,
PVLDB 7(10), 2014, without the first/last pair).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["Envelope"]


class Envelope:
    """Min/max/last envelope of a multi-component series, in bins that double when full.

    Parameters
    ----------
    components : int
        Values per sample (2 for an offset ``(x_nm, y_nm)``).
    flags : int
        Boolean flags per sample whose counts are kept per bin.
    capacity : int
        Maximum number of bins (even, at least 16).
    initial_width_s : float
        Bin width before the first merge, s.

    Notes
    -----
    Samples must arrive in non-decreasing time; an older sample is counted in
    the bin it falls in if that bin still exists, else dropped
    (:attr:`dropped`). Memory is ``capacity × (3 × components + flags + 2)``
    float64 values.
    """

    def __init__(
        self,
        *,
        components: int,
        flags: int = 0,
        capacity: int = 2048,
        initial_width_s: float = 0.05,
    ) -> None:
        if capacity < 16 or capacity % 2:
            raise ValueError(f"capacity must be an even number >= 16, got {capacity}")
        if not initial_width_s > 0:
            raise ValueError(f"initial_width_s must be > 0, got {initial_width_s}")
        self.components = components
        self.flags = flags
        self.capacity = capacity
        self.width_s = float(initial_width_s)
        self.t0_s: float | None = None
        self.n_bins = 0
        self.samples = 0
        self.dropped = 0
        #: Increments whenever existing bins change in place other than the last
        #: (a merge), so a consumer knows to resend everything.
        self.generation = 0
        self._min = np.zeros((capacity, components))
        self._max = np.zeros((capacity, components))
        self._last = np.zeros((capacity, components))
        self._count = np.zeros(capacity, dtype=np.int64)
        self._flag = np.zeros((capacity, max(flags, 1)), dtype=np.int64)

    def add(self, t_s: float, values: Sequence[float], flags: Sequence[bool] = ()) -> None:
        """Add one sample at time ``t_s`` (s); non-finite values count but do not widen."""
        if not math.isfinite(t_s):
            self.dropped += 1
            return
        if self.t0_s is None:
            self.t0_s = math.floor(t_s / self.width_s) * self.width_s
        k = int((t_s - self.t0_s) // self.width_s)
        if k < 0:
            self.dropped += 1
            return
        while k >= self.capacity:
            self._merge()
            k = int((t_s - self.t0_s) // self.width_s)
        if k >= self.n_bins:
            for j in range(self.n_bins, k + 1):
                self._count[j] = 0
                self._flag[j] = 0
                self._min[j] = math.inf
                self._max[j] = -math.inf
                self._last[j] = math.nan
            self.n_bins = k + 1
        v = np.asarray(values, dtype=np.float64)
        finite = np.isfinite(v)
        self._min[k] = np.where(finite, np.minimum(self._min[k], v), self._min[k])
        self._max[k] = np.where(finite, np.maximum(self._max[k], v), self._max[k])
        self._last[k] = v
        self._count[k] += 1
        for i, f in enumerate(flags[: self.flags]):
            if f:
                self._flag[k, i] += 1
        self.samples += 1

    def _merge(self) -> None:
        n = self.n_bins
        half = (n + 1) // 2
        for j in range(half):
            a, b = 2 * j, 2 * j + 1
            if b < n:
                self._min[j] = np.minimum(self._min[a], self._min[b])
                self._max[j] = np.maximum(self._max[a], self._max[b])
                self._last[j] = self._last[b] if self._count[b] else self._last[a]
                self._count[j] = self._count[a] + self._count[b]
                self._flag[j] = self._flag[a] + self._flag[b]
            else:
                self._min[j], self._max[j], self._last[j] = (
                    self._min[a],
                    self._max[a],
                    self._last[a],
                )
                self._count[j], self._flag[j] = self._count[a], self._flag[a]
        self.n_bins = half
        self.width_s *= 2.0
        self.generation += 1

    def arrays(self, start: int = 0) -> dict[str, npt.NDArray[Any]]:
        """Bins ``start, ...`` as arrays: ``t_s`` (bin centre), ``min``, ``max``, ``last``
        (shape (n, components), NaN for an empty component), ``count`` and ``flag``
        (counts per flag, shape (n, flags))."""
        n = self.n_bins
        start = min(max(start, 0), n)
        t0 = 0.0 if self.t0_s is None else self.t0_s
        t = t0 + (np.arange(start, n) + 0.5) * self.width_s
        lo = self._min[start:n].copy()
        hi = self._max[start:n].copy()
        lo[~np.isfinite(lo)] = np.nan
        hi[~np.isfinite(hi)] = np.nan
        return {
            "t_s": t,
            "min": lo,
            "max": hi,
            "last": self._last[start:n].copy(),
            "count": self._count[start:n].copy(),
            "flag": self._flag[start:n, : self.flags].copy(),
        }

    def nbytes(self) -> int:
        """Memory held by the bins, bytes (constant after construction)."""
        return int(
            self._min.nbytes
            + self._max.nbytes
            + self._last.nbytes
            + self._count.nbytes
            + self._flag.nbytes
        )
