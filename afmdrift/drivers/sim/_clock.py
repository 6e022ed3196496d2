"""The virtual clock of the simulator's servers."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

__all__ = ["VirtualClock"]


class VirtualClock:
    """Virtual seconds that run ``speed`` times faster than ``wall()`` seconds.

    Parameters
    ----------
    speed : float
        Virtual seconds per wall second (1.0 real time; 1000 runs 8 h in under 30 s).
    start_s : float
        Virtual time now.
    wall : callable
        Wall clock in s (default :func:`time.monotonic`).
    """

    def __init__(
        self,
        *,
        speed: float = 1.0,
        start_s: float = 0.0,
        wall: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (np.isfinite(speed) and speed > 0):
            raise ValueError(f"speed must be a positive number, got {speed!r}")
        self.speed = float(speed)
        self._wall = wall
        self._wall0 = wall()
        self._start_s = float(start_s)

    def now_s(self) -> float:
        return self._start_s + self.speed * (self._wall() - self._wall0)
