"""Candidates read from the drift itself: a cycle, a jump, a change of rate.

The library and the generic families test what was logged. What nobody
logged (an air handler cycling every half hour, a sample that slips once, a
door that changes the drift rate) shows only in the drift. Three drift-shape
terms (:class:`~afmdrift.model.DriftShape`, ``docs/model.md``) describe it:
``periodic:period_s=P``, ``jump:t_s=t`` and ``rate_change:t_s=t``.

Here each becomes one candidate whose nonlinear parameter is searched over
every position the data can resolve, and it goes through the same
added-variable test as every other candidate
(:func:`~afmdrift.diagnostics._candidates.evaluate_candidate`): the best
position on the grid, refined between its neighbours, and blocked
cross-validation that searches again on each training set. **The search is
paid for** in the Bonferroni factor of the diagnosis: a jump or a kink adds
one test per frame boundary searched, a cycle one per independent frequency
between the shortest and the longest period searched (the Fourier
resolution 1/span; the grid is three times finer, so the best period is not
missed between two of them). A found candidate is then named by the term a
user pastes, with its position fixed (``jump:t_s=19200``). A cycle must also
be steady (:func:`cycle_steadiness`): the unlogged drift of a real instrument
may oscillate for an hour or two and die out (a damped, AR(2)-like wander),
which a sinusoid fits for a while; a cycle that a user can log or model keeps
its amplitude and phase over the record. And a cycle that a logged channel
carries (:func:`channel_following`) is that channel's to explain: "a cycle
that no logged channel follows" is said only when none does.

Where a jump is searched is not limited by the events: a discovered jump is
offered even next to a logged event of another kind (a file boundary of the
controller at the moment the tip changed), because the event kind's own
term, tested beside it, is what says whether the kind explains it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from afmdrift.diagnostics._candidates import CandidateResult, ModelDesign
from afmdrift.model import DriftShape, History, parse_term_spec

__all__ = [
    "CHANNEL_FOLLOWS_POWER",
    "DISCOVERED_KINDS",
    "FREQUENCY_OVERSAMPLING",
    "MIN_CYCLE_FRAMES",
    "MIN_SIDE_FRAMES",
    "STEADY_FRACTION",
    "channel_following",
    "cycle_steadiness",
    "discovered_terms",
    "fix_discovered",
    "search_tests",
]

FloatArray = npt.NDArray[np.float64]

#: The drift shapes searched, in the order they are listed.
DISCOVERED_KINDS = ("periodic", "jump", "rate_change")

#: A jump or a kink is searched only where this many fed frames lie on each side
#: (fewer cannot tell a step from the model's start or its last prediction).
MIN_SIDE_FRAMES = 4

#: The shortest cycle searched spans this many frame intervals (a shorter one
#: is aliased by the frames).
MIN_CYCLE_FRAMES = 3.0

#: The period grid is this many times finer than the Fourier resolution 1/span.
FREQUENCY_OVERSAMPLING = 3


def discovered_terms(design: ModelDesign, model_terms: Sequence[str]) -> list[DriftShape]:
    """The three searched drift-shape candidates of ``design`` (fewer on a short record).

    Each is a :class:`~afmdrift.model.DriftShape` whose ``searched`` values
    are the positions tried and whose ``searched_tests`` is what the search
    costs in the Bonferroni factor (:func:`search_tests`).
    """
    t = np.asarray(design.t_s, dtype=np.float64)
    n = t.size
    out: list[DriftShape] = []
    if n < 2 * MIN_SIDE_FRAMES + 2:
        return out
    span = float(t[-1] - t[0])
    step = float(np.median(np.diff(t)))
    if not (span > 0 and step > 0):
        return out
    f_lo, f_hi = STEADY_PARTS * STEADY_MIN_CYCLES / span, 1.0 / (MIN_CYCLE_FRAMES * step)
    if f_hi > f_lo:
        freqs = np.arange(f_lo, f_hi, 1.0 / (FREQUENCY_OVERSAMPLING * span))
        periods = np.sort(1.0 / freqs)
        tests = max(1, math.ceil((f_hi - f_lo) * span))
        out.append(_searched("periodic", "period_s", periods, tests, model_terms))
    bounds = 0.5 * (t[:-1] + t[1:])
    where = bounds[MIN_SIDE_FRAMES - 1 : n - MIN_SIDE_FRAMES]
    if where.size:
        for kind in ("jump", "rate_change"):
            out.append(_searched(kind, "t_s", where, where.size, model_terms))
    return out


def _searched(
    kind: str, where: str, values: FloatArray, tests: int, model_terms: Sequence[str]
) -> DriftShape:
    lo, hi = float(values.min()), float(values.max())
    spec = f"{kind}:{where}={lo:.6g}..{max(hi, lo * 1.000001):.6g}"
    cls = parse_term_spec(spec)
    term = cls()
    assert isinstance(term, DriftShape)
    vars(term)["searched"] = np.asarray(values, dtype=np.float64)
    vars(term)["searched_tests"] = int(tests)
    vars(term)["taken"] = tuple(model_terms)
    return term


#: A cycle is steady when, fitted on each part of the record alone, it carries
#: at least this fraction of the whole record's cycle in phase (its projection
#: on it): a damped oscillation of the unlogged drift (an AR(2) process)
#: changes its phase from part to part; a thermostat does not.
STEADY_FRACTION = 0.5

#: The record is cut into this many parts for the steadiness of a cycle, each
#: holding at least :data:`STEADY_MIN_CYCLES` periods; so the longest cycle
#: searched repeats 8 times in the record. A slower oscillation cannot be told
#: from the unlogged wander of the drift (a damped oscillation of an hour or
#: two looks like a cycle over a few repeats), nor shown to be steady.
STEADY_PARTS = 4
STEADY_MIN_CYCLES = 2.0


def cycle_steadiness(
    term: DriftShape, design: ModelDesign, history: History, base: object, period_s: float
) -> float:
    """How steady a cycle of ``period_s`` is over the record: the smallest, over
    :data:`STEADY_PARTS` consecutive parts, of the projection of the cycle
    fitted on that part alone on the cycle fitted on the whole record
    (1: the same amplitude and phase everywhere; 0 or less: absent or out of
    phase in some part). Fits are on the model's partialled quasi-differences,
    like the candidate test, both axes together. NaN when it cannot be said."""
    from afmdrift.diagnostics._candidates import _cand_block

    t = design.t_s[1:]
    span = float(t[-1] - t[0]) if t.size > 1 else 0.0
    parts = STEADY_PARTS
    if span < 0.999 * parts * STEADY_MIN_CYCLES * period_s:
        return math.nan
    blocks = _cand_block(term, design.samples, history, design.scan_sign, {term.where: period_s})
    edges = np.linspace(t[0], t[-1] + 1e-9, parts + 1)
    whole: list[FloatArray] = []
    by_part: list[list[FloatArray]] = [[] for _ in range(parts)]
    for a in (0, 1):
        raw = design.qd(np.asarray(blocks[a], dtype=np.float64), a)
        q = base.qm[a]  # type: ignore[attr-defined]
        z = raw - q @ (q.T @ raw)
        e = base.e0[a]  # type: ignore[attr-defined]
        whole.append(np.linalg.lstsq(z, e, rcond=1e-10)[0])
        for k in range(parts):
            sel = (t >= edges[k]) & (t < edges[k + 1])
            if sel.sum() <= 2 * z.shape[1]:
                return math.nan
            by_part[k].append(np.linalg.lstsq(z[sel], e[sel], rcond=1e-10)[0])
    c_all = np.concatenate(whole)
    norm = float(c_all @ c_all)
    if not norm > 0:
        return math.nan
    return min(float(np.concatenate(c) @ c_all) / norm for c in by_part)


#: A logged channel follows a cycle when a sinusoid of the cycle's period
#: explains this fraction of its variance, a straight line removed (the
#: threshold at which the errors' own periodogram is called periodic,
#: :func:`~afmdrift.diagnostics._finding.error_patterns`).
CHANNEL_FOLLOWS_POWER = 0.3


def channel_following(history: History, period_s: float) -> str | None:
    """The logged channel that carries a cycle of ``period_s`` (see
    :data:`CHANNEL_FOLLOWS_POWER`), or None: then the cycle is the channel's
    to explain (its generic and library terms), not an unlogged one."""
    t = np.asarray(history.channel_t_s, dtype=np.float64)
    if t.size < 8 or not period_s > 0:
        return None
    best, name_best = 0.0, None
    for name in sorted(history.channels):
        v = np.asarray(history.channels[name], dtype=np.float64)
        ok = np.isfinite(v)
        if ok.sum() < 8:
            continue
        tt, vv = t[ok], v[ok]
        line = np.column_stack([np.ones_like(tt), tt - tt.mean()])
        r = vv - line @ np.linalg.lstsq(line, vv, rcond=None)[0]
        total = float(r @ r)
        if not total > 0:
            continue
        phase = 2.0 * np.pi * tt / period_s
        wave = np.column_stack([np.sin(phase), np.cos(phase), line])
        rest = vv - wave @ np.linalg.lstsq(wave, vv, rcond=None)[0]
        power = 1.0 - float(rest @ rest) / total
        if power >= CHANNEL_FOLLOWS_POWER and power > best:
            best, name_best = power, name
    return name_best


def search_tests(term: object, grid_size: int) -> int:
    """The tests a candidate counts in the Bonferroni factor: its grid, or for a
    searched drift shape the independent positions searched."""
    tests = vars(term).get("searched_tests") if hasattr(term, "__dict__") else None
    return int(tests) if tests is not None else grid_size


def fix_discovered(result: CandidateResult, term: DriftShape) -> None:
    """Name a searched candidate by the term a user pastes: its best position
    fixed (``jump:t_s=19200``), and say what it is in ``result.discovered``."""
    value = result.nonlinear.get(term.where, math.nan)
    if not math.isfinite(value):
        return
    spec = f"{term.shape}:{term.where}={value:.0f}"
    taken = set(vars(term).get("taken", ()))
    if spec in taken:
        k = 2
        while f"{spec}#{k}" in taken:
            k += 1
        spec = f"{spec}#{k}"
    result.effect = spec
    found: dict[str, object] = {"kind": term.shape, term.where: float(round(value))}
    p = result.params
    if term.shape == "periodic":
        amp = [math.hypot(p.get(f"sin_nm_{a}", 0.0), p.get(f"cos_nm_{a}", 0.0)) for a in "xy"]
        found["amplitude_nm"] = [_finite(v) for v in amp]
    elif term.shape == "jump":
        found["step_nm"] = [_finite(p.get(f"step_nm_{a}", math.nan)) for a in "xy"]
    else:
        found["rate_change_nm_per_h"] = [
            _finite(p.get(f"rate_change_nm_per_h_{a}", math.nan)) for a in "xy"
        ]
    result.discovered = found


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None
