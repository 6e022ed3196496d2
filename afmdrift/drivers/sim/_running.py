"""A simulated instrument running on a virtual clock, for the protocol servers.

Both servers (the line protocol of ``docs/protocol.md`` and the Nanonis TCP
protocol) serve one :class:`RunningSimulation`: a periodic tick advances the
simulation to the clock's now in worker threads, so frames complete while
nobody asks, and each command first advances by at most one step
(:attr:`RunningSimulation.step_s`). When the physics cannot keep up with the
clock's speed the instrument's time falls behind the nominal virtual clock
rather than skipping.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Protocol

from afmdrift.drivers.sim._clock import VirtualClock

__all__ = ["Advancing", "RunningSimulation"]


class Advancing(Protocol):
    """What the runner needs from a simulation."""

    @property
    def now_s(self) -> float: ...
    def advance_to(self, t_s: float, *, render_all: bool = True) -> object: ...


class RunningSimulation:
    """Advance ``sim`` along ``clock``: a background tick and bounded steps.

    Parameters
    ----------
    sim : Advancing
        The simulated instrument; only touch it while holding :attr:`lock`.
    clock : VirtualClock
    tick_s : float
        Wall seconds between background advances.
    """

    def __init__(self, sim: Advancing, *, clock: VirtualClock, tick_s: float) -> None:
        if not tick_s > 0:
            raise ValueError(f"tick_s must be > 0, got {tick_s!r}")
        self.sim = sim
        self.clock = clock
        self.tick_s = tick_s
        self.lock = threading.Lock()  # the simulator runs in worker threads
        self.stopping = threading.Event()
        self._ticker: asyncio.Task[None] | None = None

    def start(self) -> None:
        """Start the background tick (no effect while it runs)."""
        self.stopping.clear()
        if self._ticker is None or self._ticker.done():
            self._ticker = asyncio.create_task(self._tick(), name="sim-server-tick")

    def take_ticker(self) -> asyncio.Task[None] | None:
        """Stop advancing; return the tick task (to cancel and await) if any."""
        self.stopping.set()
        ticker, self._ticker = self._ticker, None
        return ticker

    async def _tick(self) -> None:
        while True:
            await asyncio.to_thread(self.advance)
            await asyncio.sleep(self.tick_s)

    def advance(self) -> None:
        """Run the simulation up to the virtual clock's now (thread-safe).

        Advances in steps of :attr:`step_s` virtual seconds, releasing the lock
        between steps, so commands are answered and a stop returns promptly
        even when the physics lags behind a high speed. Frames that a later
        frame of the same step supersedes are not rendered
        (``render_all=False``): only the last completed frame is served, so
        nobody could fetch them.
        """
        target = self.clock.now_s()
        while not self.stopping.is_set():
            with self.lock:
                if not self.advance_step_locked(target):
                    return

    @property
    def step_s(self) -> float:
        """Largest virtual time one physics step covers: a quarter of a tick."""
        return max(0.25 * self.tick_s * self.clock.speed, 1e-3)

    def advance_step_locked(self, target_s: float) -> bool:
        """Advance by at most one step towards ``target_s``; ``False`` once there."""
        now = self.sim.now_s
        if now >= target_s:
            return False
        self.sim.advance_to(min(now + self.step_s, target_s), render_all=False)
        return True
