"""Block phase-correlation drift measurement (Yang et al., IEEE T-NANO 2008).

Sign convention (used everywhere in afmdrift): a feature at image position
``u`` in the reference appears at ``u + d`` in the current frame. x runs
along columns (the fast scan axis), y along rows; pixel sizes are ``(x, y)``.

Public API
----------
:func:`measure_drift`
    Drift between two height images, with per-block detail and uncertainty.
:class:`DriftTracker`
    Streaming registration with cached reference spectra (consecutive or
    keyframe references).
:class:`DriftResult`, :class:`BlockField`, :class:`TrackStep`
    Result records.
:func:`warm_up`
    Compile (or load) the engine's kernels ahead of the first frame.
:func:`coarse_shift`, :class:`CoarseShift`
    The whole-image integer pre-alignment ``measure_drift`` uses when no
    prior is given (line-levelled heights, checked by the x-gradient).
:class:`RegistrationConfig`
    The ``[registration]`` configuration section.
:class:`RegistrationError`, :class:`InvalidFrameError`
    Typed input errors (both are :class:`afmdrift.errors.InputError`).

See ``docs/registration.md`` for the method, design choices and accuracy.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from afmdrift.config import RegistrationConfig
from afmdrift.registration._errors import InvalidFrameError, RegistrationError

if TYPE_CHECKING:
    from afmdrift.registration._coarse import CoarseShift, coarse_shift
    from afmdrift.registration._measure import measure_drift, warm_up
    from afmdrift.registration._result import BlockField, DriftResult
    from afmdrift.registration._tracker import DriftTracker, TrackStep

__all__ = [
    "BlockField",
    "CoarseShift",
    "DriftResult",
    "DriftTracker",
    "InvalidFrameError",
    "RegistrationConfig",
    "RegistrationError",
    "TrackStep",
    "coarse_shift",
    "measure_drift",
    "warm_up",
]

# The engine (pyFFTW, work arrays) loads on first use, so that importing the
# configuration (afmdrift.config) or the CLI stays light.
_LAZY = {
    "measure_drift": "afmdrift.registration._measure",
    "warm_up": "afmdrift.registration._measure",
    "BlockField": "afmdrift.registration._result",
    "CoarseShift": "afmdrift.registration._coarse",
    "coarse_shift": "afmdrift.registration._coarse",
    "DriftResult": "afmdrift.registration._result",
    "DriftTracker": "afmdrift.registration._tracker",
    "TrackStep": "afmdrift.registration._tracker",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
