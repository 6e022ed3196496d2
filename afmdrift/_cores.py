"""How many cores this process may run on: one count for every layer that
sizes a pool by it (the registration's block threads, the runs layer's
processes, ``afmdrift batch``'s LocalCluster). It imports nothing of the
package, so a command that only needs the count (``afmdrift batch``'s client)
does not load the numerical stack."""

from __future__ import annotations

import os

__all__ = ["available_cores"]


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, else the CPU count)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(os.cpu_count() or 1, 1)
