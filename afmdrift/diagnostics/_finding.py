"""A diagnosis in words: the patterns of the errors and the finding.

:func:`error_patterns` names the session-wide regularities of the one-step
errors (autocorrelation, a period, a channel they follow, up/down frames,
jumps of the measured drift); :func:`finding_text` states the missing effect
(or that none was found) with its evidence and the configuration line to
add; :func:`describe_driver` says what a generic term responds to.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from afmdrift.config import PhysicsConfig
from afmdrift.diagnostics._candidates import CandidateResult, Thresholds
from afmdrift.diagnostics._data import RunData
from afmdrift.diagnostics._diagnosis import DiagnoseOptions
from afmdrift.diagnostics._model_run import ModelRun
from afmdrift.diagnostics._stats import cross_correlation, robust_z
from afmdrift.model import CHANNEL_TAU_RANGE_S, EffectTerm, available_terms, term_class
from afmdrift.records import EventKind

__all__ = [
    "JUMP_MOVE_FRACTION",
    "JUMP_MOVE_SIZE",
    "JUMP_Z",
    "describe_driver",
    "describe_shape",
    "error_patterns",
    "finding_text",
    "jumps",
    "plain_finding",
    "with_jump_caution",
]

FloatArray = npt.NDArray[np.float64]


def error_patterns(
    data: RunData,
    run: ModelRun,
    burn: int,
    lb: dict[str, dict[str, float]],
    pg: dict[str, dict[str, float]],
    up_down: dict[str, float] | None,
) -> list[str]:
    """Session-wide regularities of the one-step errors, in plain language."""
    out: list[str] = []
    e = run.errors_nm[burn:]
    n = int(np.all(np.isfinite(e), axis=1).sum())
    for axis in ("x", "y"):
        p = lb[axis]["p_value"]
        if math.isfinite(p) and p < 0.01:
            out.append(
                f"{axis} errors are autocorrelated (Ljung-Box p = {p:.2g} over "
                f"{int(lb[axis]['lags'])} lags): something systematic is left in them"
            )
        power, period = pg[axis]["peak_power"], pg[axis]["peak_period_s"]
        if math.isfinite(power) and power > 0.3:
            out.append(
                f"{axis} errors have a periodic component of {period / 3600:.2g} h "
                f"(a sinusoid explains {100 * power:.0f}% of their variance)"
            )
    if n >= 10:
        threshold = max(0.3, 3.0 / math.sqrt(n))
        for name in data.channel_names():
            ct, cv = data.channel_series(name)
            if ct.size < 2:
                continue
            x = np.interp(run.t_s, ct, cv)
            dx = np.concatenate([[np.nan], np.diff(x)])[burn:]
            for a, axis in enumerate("xy"):
                lags, r = cross_correlation(e[:, a], dx, max_lag=3)
                if not np.isfinite(r).any():
                    continue
                i = int(np.nanargmax(np.abs(r)))
                if abs(r[i]) > threshold:
                    out.append(
                        f"{axis} errors follow the changes of {name} (correlation "
                        f"{r[i]:+.2f} at a lag of {int(lags[i])} frame(s))"
                    )
    if up_down is not None and up_down["p_value"] < 0.001:
        out.append(
            f"up and down frames differ: mean error up minus down is "
            f"{up_down['diff_x_nm']:+.2f} nm in x, {up_down['diff_y_nm']:+.2f} nm in y "
            f"(Welch p = {up_down['p_value']:.2g})"
        )
    for k, jump in jumps(run):
        out.append(
            f"the measured drift jumps by ({jump[0]:+.0f}, {jump[1]:+.0f}) nm at "
            f"t = {run.t_s[k]:.0f} s (frame {int(run.frames[k])}), far beyond its other "
            "frame-to-frame changes: a registration mis-lock or a tip change? Check the "
            "worst frame's vector field before trusting a finding"
        )
    return out


#: A frame-to-frame change of p this many robust σ beyond the median is a jump.
JUMP_Z = 20.0


#: After an offset move, a change of p larger than this fraction of the move
#: is a jump (creep and hysteresis stay well below it).
JUMP_MOVE_FRACTION = 0.5


#: ... for moves this many times the median frame-to-frame change of p; the
#: smaller moves of a closed loop following the drift are judged like frames
#: without a move.
JUMP_MOVE_SIZE = 5.0


def jumps(run: ModelRun) -> list[tuple[int, FloatArray]]:
    """Frames whose measured position jumps implausibly, as (index into the
    run, jump (x, y) in nm): a robust z of the Euclidean increment above
    :data:`JUMP_Z`, or, across an offset move of more than
    :data:`JUMP_MOVE_SIZE` median increments, an increment larger than
    :data:`JUMP_MOVE_FRACTION` of the move."""

    inc = np.diff(run.measured_nm, axis=0)
    if inc.shape[0] < 8:
        return []
    size = np.hypot(inc[:, 0], inc[:, 1])
    z = robust_z(size)
    typical = float(np.nanmedian(size))
    mt, steps = run.history.of_kind(EventKind.OFFSET_MOVE)
    moved_by = np.hypot(steps[:, 0], steps[:, 1])
    out: list[tuple[int, FloatArray]] = []
    for i in range(inc.shape[0]):
        t0, t1 = run.t_s[i], run.t_s[i + 1]
        moved = float(moved_by[(mt > t0) & (mt <= t1)].sum())
        if moved > JUMP_MOVE_SIZE * typical:
            if size[i] > JUMP_MOVE_FRACTION * moved:
                out.append((i + 1, inc[i]))
        elif z[i] > JUMP_Z:
            out.append((i + 1, inc[i]))
    return out


def with_jump_caution(finding: str, run: ModelRun) -> str:
    """``finding`` prefixed with a caution when the measured drift jumps (see
    :func:`jumps`), also when the finding is a jump discovered there: a
    registration mis-lock makes the same step as a slipping sample."""
    found_jumps = jumps(run)
    if not found_jumps:
        return finding
    k, jump = found_jumps[0]
    return (
        f"Caution: the measured drift jumps by ({jump[0]:+.0f}, {jump[1]:+.0f}) nm at "
        f"t = {run.t_s[k]:.0f} s ({len(found_jumps)} such jump(s)); if that is a "
        f"measurement error, what follows may explain it rather than physics. {finding}"
    )


def _format_params(c: CandidateResult) -> str:
    """Fitted parameters in words: θ, linear coefficients per axis, refitted model θ."""
    parts = [f"{k} = {v:.3g}" for k, v in c.params.items() if k in c.nonlinear]
    lin: dict[str, list[str]] = {}
    model: list[str] = []
    for k, v in c.params.items():
        if k in c.nonlinear:
            continue
        if k.startswith("model."):
            model.append(f"{k.removeprefix('model.')} = {v:.3g}")
            continue
        base, _, axis = k.rpartition("_")
        lin.setdefault(base, []).append(f"{axis} = {v:.3g}")
    for base, vals in lin.items():
        parts.append(f"{base}: {', '.join(vals)}")
    text = "; ".join(parts)
    if model:
        text += f" (model terms refitted with it: {', '.join(model)})"
    return text


def finding_text(
    top: CandidateResult | None,
    results: list[CandidateResult],
    physics: PhysicsConfig,
    summary: dict[str, float],
    after_summary: dict[str, float] | None,
    n_tests: int,
    options: DiagnoseOptions,
) -> tuple[str, list[str] | None]:
    th = options.thresholds
    rule = (
        f"online re-run one-step error at least {100 * th.min_effect:.0f}% lower, and either "
        f"ΔAICc > {th.min_delta_aicc:g} with HAC Wald p < {th.alpha:g} after Bonferroni over "
        f"{n_tests} tests and a blocked-CV error at least {100 * th.min_cv_drop:.0f}% lower "
        f"({100 * th.generic_min_drop:.0f}% for a generic term), or a Diebold-Mariano "
        f"p < {th.alpha:g} of the re-run, Holm-adjusted over the re-runs"
    )
    if top is None:
        testable = [c for c in results if c.testable]
        n_shapes = sum(1 for c in testable if "drift_shape" in c.driver)
        n_generic = sum(1 for c in testable if c.driver) - n_shapes
        best = (
            f" The closest candidate is {testable[0].effect} ({testable[0].evidence()})."
            if testable
            else ""
        )
        shapes = (
            f" and none of the {n_shapes} shapes searched in the drift itself (a cycle, a "
            "jump, a change of rate)"
            if n_shapes
            else ""
        )
        return (
            f"Nothing is missing that these data can show: none of the "
            f"{len(testable) - n_generic - n_shapes} testable "
            f"library effects not in the model, none of the {n_generic} generic terms "
            f"(every logged channel and event kind){shapes} passes the test ({rule}).{best}",
            None,
        )
    terms = [*physics.terms, top.effect]
    alike = _alike_text(top, results)
    if top.driver:
        return _generic_finding(top, results, terms, summary, after_summary) + alike, terms
    doc = (type(_term_instance(top.effect, physics)).__doc__ or "").strip().splitlines()[0]
    change = _error_change(summary, after_summary)
    return (
        f"Missing effect: {top.effect} ({doc.rstrip('.')}). Fitted: {_format_params(top)}. "
        f"Evidence: {top.evidence()}.{change}{alike} To add it, put in your configuration "
        f"file: [model.physics] terms = "
        f"[{', '.join(repr(t).replace(chr(39), chr(34)) for t in terms)}]",
        terms,
    )


def _alike_text(top: CandidateResult, results: list[CandidateResult]) -> str:
    """What the finding cannot tell its top candidate from, and what would."""
    if not top.alike:
        return ""
    others = [c for c in results if c.effect in top.alike]
    names = ", ".join(c.effect for c in others)
    lead = "the library effect is named first; " if not top.driver else ""
    kinds = {c.driver.get("event_kind") for c in [top, *others] if c.driver.get("event_kind")}
    channels = {c.channel for c in [top, *others] if c.channel}
    apart = ["a longer record"]
    event_named = not top.driver and top.effect in ("warmup", "creep", "hysteresis", "tip_change")
    if kinds or event_named:
        apart.append("more of the events that drive them (a second power cycle, more moves)")
    if channels:
        apart.append("a second sensor, or a period in which the channel changes alone")
    return (
        f" On these data it cannot be told apart from {names} (their online re-run errors "
        f"do not differ significantly); {lead}what would tell them apart: "
        f"{', or '.join(apart)}."
    )


def _duration(t_s: float) -> str:
    """A time constant in words: s below 2 min, min below 2 h, else h."""
    if t_s < 120:
        return f"{t_s:.0f} s"
    if t_s < 7200:
        return f"{t_s / 60:.0f} min"
    return f"{t_s / 3600:.1f} h"


#: How the unit suffixes of channel names read in sentences.
_UNIT_WORDS = {"c": "K", "k": "K", "hpa": "hPa", "pa": "Pa", "pct": "%", "mw": "mW", "v": "V"}


def _gains(c: CandidateResult) -> str:
    """The linear coefficients of ``c`` per axis in words (``+4.1 nm/hPa in x, ...``)."""
    parts = []
    for k, v in c.params.items():
        if k in c.nonlinear or k.startswith("model.") or not math.isfinite(v):
            continue
        base, _, axis = k.rpartition("_")
        if base.startswith("gain_nm_per_"):
            suffix = base.removeprefix("gain_nm_per_")
            unit = f"nm/{_UNIT_WORDS.get(suffix, suffix)}"
        else:
            unit = (
                base.replace("amplitude_nm", "nm")
                .replace("nm_per_decade", "nm per decade")
                .replace("rate_change_nm_per_h", "nm/h")
                .replace("step_nm", "nm")
                .replace("sin_nm", "nm (sine)")
                .replace("cos_nm", "nm (cosine)")
            )
        parts.append(f"{v:+.3g} {unit} in {axis}")
    return ", ".join(parts)


def describe_driver(c: CandidateResult) -> str:
    """The driver, shape, lag and gain of a generic candidate in plain language."""
    d = c.driver
    if "drift_shape" in d:
        return f"{describe_shape(c)} ({_gains(c)})"
    if "channel" in d:
        tau = c.nonlinear.get("tau_s", c.params.get("tau_s", math.nan))
        lag = (
            "directly (no lag)"
            if not math.isfinite(tau) or tau <= CHANNEL_TAU_RANGE_S[0]
            else f"through a first-order lag of about {_duration(tau)} (tau_s = {tau:.3g})"
        )
        return f"the residual follows the logged channel {d['channel']} {lag}, {_gains(c)}"
    kind = d.get("event_kind", "?")
    each = "each" in c.effect.split("#")[0].split(":")[2:]
    per = "each event with its own amplitude" if each else "the same amplitude for every event"
    if d.get("shape") == "log":
        t0 = c.nonlinear.get("t0_s", math.nan)
        return (
            f"the residual creeps logarithmically after each logged {kind} event "
            f"(t0 = {t0:.3g} s; {per}), {_gains(c)}"
        )
    tau = c.nonlinear.get("tau_s", math.nan)
    return (
        f"the residual steps after each logged {kind} event and settles exponentially "
        f"with a time constant of about {_duration(tau)} (tau_s = {tau:.3g}; {per}), {_gains(c)}"
    )


def _clock(t_s: float) -> str:
    """A time from the session's start in words: ``5 h 20 min``, ``42 min``."""
    minutes = round(t_s / 60.0)
    if minutes < 60:
        return f"{minutes} min"
    h, m = divmod(minutes, 60)
    return f"{h} h {m} min" if m else f"{h} h"


def _number(v: object) -> float:
    """A number of a ``discovered`` field (NaN for null or anything else)."""
    return float(v) if isinstance(v, int | float) else math.nan


def _pair(v: object, fmt: str = "+.0f") -> str:
    """An (x, y) pair of a ``discovered`` field in words: ``(−136, +168)``."""
    if not isinstance(v, list | tuple) or len(v) != 2:
        return "(?, ?)"
    x, y = (_number(a) for a in v)
    return f"({format(x, fmt)}, {format(y, fmt)})".replace("-", "\u2212")


def describe_shape(c: CandidateResult) -> str:
    """A discovered drift shape in the user's words, with what it may be
    (``a 31-min cycle of 4.2 nm that no logged channel follows: an air
    handler or a thermostat?``)."""
    d = c.discovered or {}
    kind = d.get("kind", c.driver.get("drift_shape"))
    if kind == "periodic":
        period = _number(d.get("period_s"))
        amp = d.get("amplitude_nm")
        size = math.hypot(*(_number(a) for a in amp)) if isinstance(amp, list) else math.nan
        return (
            f"a {_duration(period).replace(' ', '-')} cycle of {size:.2g} nm that no logged "
            "channel follows: an air handler or a thermostat?"
        )
    t = _number(d.get("t_s"))
    if kind == "jump":
        return (
            f"a jump of {_pair(d.get('step_nm'))} nm at {_clock(t)} that no logged event "
            "explains: a slip or a tip change?"
        )
    return (
        f"a change of the drift rate by {_pair(d.get('rate_change_nm_per_h'), '+.2g')} nm/h "
        f"at {_clock(t)} that no logged event explains: a door, a chiller, a switched "
        "instrument?"
    )


#: What to log instead of adding a discovered shape, by its kind.
_LOG_INSTEAD = {
    "periodic": "Log the room temperature near the instrument, or add",
    "jump": "Add",
    "rate_change": "Add",
}
_LOG_AFTER = {
    "periodic": "",
    "jump": " (or log tip changes and slips as events)",
    "rate_change": " (or log what changed then as an event)",
}


def _seen_not_helping(results: list[CandidateResult], th: Thresholds) -> str | None:
    """The plain paragraph when nothing is missing but the drift itself shows a
    jump whose in-sample evidence passes (its search over every frame boundary
    paid for) although adding it does not help the model predict: said, with
    what to log. Only a jump: no model predicts it at its frame, and the
    AR(1) residual follows the new level from the next frame on, so a real
    jump can leave the predictions as good without its term; a cycle or a
    change of rate that is real makes the predictions better. A jump is
    rarely cross-validated (its one frame falls in one fold), so its evidence
    must be as strong as a named effect's without cross-validation: ΔAICc
    above ``no_cv_factor × min_delta_aicc`` and the Bonferroni p below
    ``alpha / no_cv_factor``."""
    seen = [
        c
        for c in results
        if c.discovered is not None
        and c.discovered.get("kind") == "jump"
        and c.delta_aicc > th.no_cv_factor * th.min_delta_aicc
        and c.p_bonferroni < th.alpha / th.no_cv_factor
        and c.rmse_after_kind == "replayed"
        and c.prequential_drop is not None
    ]
    if not seen:
        return None
    c = max(seen, key=lambda c: c.delta_aicc)
    drop = c.prequential_drop or 0.0
    change = f"{100 * abs(drop):.0f} % {'lower' if drop >= 0 else 'higher'}"
    where = " on the frames after it" if (c.discovered or {}).get("kind") == "jump" else ""
    log = {
        "periodic": "log the room temperature near the instrument",
        "jump": "log tip changes and slips as events",
        "rate_change": "log what changed then as an event",
    }.get(str((c.discovered or {}).get("kind")), "log what happened then")
    return (
        f"Nothing the model lacks would make it predict better, but the drift itself shows "
        f"{describe_shape(c)} Adding `{c.effect}` does not help the predictions enough to "
        f"matter (the one-step error{where} is {change} with it), so {log} rather than "
        "model it."
    )


def plain_finding(
    top: CandidateResult | None,
    results: list[CandidateResult],
    summary: dict[str, float],
    after_summary: dict[str, float] | None,
    thresholds: Thresholds | None = None,
) -> str:
    """The finding in two plain sentences: what is missing, what to add and how
    much it helps; or that nothing is (and a jump the drift shows, if any)."""
    before = summary.get("rmse_nm", math.nan)
    if top is None:
        seen = _seen_not_helping(results, thresholds or Thresholds())
        if seen is not None:
            return seen
        n = sum(1 for c in results if c.testable)
        return (
            f"Nothing is missing that these data can show: none of the {n} effects, logged "
            "responses and drift shapes tested improves the model's predictions enough to "
            f"matter. Keep the model as it is (its one-step error is {before:.2f} nm RMS)."
        )
    helps = ""
    after = after_summary["rmse_nm"] if after_summary is not None else math.nan
    if top.rmse_after_kind == "replayed" and top.rmse_after_nm is not None:
        # A discovered jump is compared without the frames of the jump itself.
        before = top.rmse_base_nm if top.rmse_base_nm is not None else before
        after = top.rmse_after_nm
    if math.isfinite(after) and before > 0:
        besides = " on the frames after it" if (top.discovered or {}).get("kind") == "jump" else ""
        helps = (
            f"; with it the one-step error{besides} falls from {before:.2f} to {after:.2f} nm "
            f"RMS ({100 * (1 - after / before):.0f} % lower)"
        )
    if "drift_shape" in top.driver:
        kind = top.driver["drift_shape"]
        return (
            f"Missing: {describe_shape(top)} {_LOG_INSTEAD[kind]} `{top.effect}` to "
            f"[model.physics] terms{_LOG_AFTER[kind]}{helps}."
        )
    if top.driver:
        what = (
            f"a response to the logged channel {top.driver['channel']}"
            if "channel" in top.driver
            else f"a response to the logged {top.driver.get('event_kind', '?')} events"
        )
        return (
            f"Missing: {what}, which no library effect explains. Add `{top.effect}` to "
            f"[model.physics] terms{helps}."
        )
    return (
        f"Missing: the library effect {top.effect}. Add `{top.effect}` to "
        f"[model.physics] terms{helps}."
    )


def _generic_finding(
    top: CandidateResult,
    results: list[CandidateResult],
    terms: list[str],
    summary: dict[str, float],
    after_summary: dict[str, float] | None,
) -> str:
    """The finding for a generic term: no library effect explains it; driver and shape."""
    named = [c for c in results if c.testable and not c.driver]
    closest = (
        f" (the closest, {named[0].effect}, has ΔAICc = {named[0].delta_aicc:.1f}"
        f"{', significant but far behind' if named[0].significant else ', not significant'})"
        if named
        else ""
    )
    change = _error_change(summary, after_summary)
    quoted = ", ".join(f'"{t}"' for t in terms)
    return (
        f"Missing effect outside the library: {describe_driver(top)}. No library effect "
        f"explains it{closest}. Term: {top.effect}. Evidence: {top.evidence()}.{change} "
        f"To add this term, put in your configuration file: [model.physics] terms = [{quoted}] "
        f"(or --effects {','.join(terms)})."
    )


def _term_instance(name: str, physics: PhysicsConfig) -> EffectTerm:
    return term_class(name, available_terms(physics.plugins))()


def _error_change(summary: dict[str, float], after_summary: dict[str, float] | None) -> str:
    """The finding's sentence on how much adding the candidate cuts the
    one-step error ("" when the model was not re-run with it)."""
    if after_summary is None or not summary["rmse_nm"] > 0:
        return ""
    drop = 1.0 - after_summary["rmse_nm"] / summary["rmse_nm"]
    return (
        f" Re-running the model with it cuts the one-step RMS error from "
        f"{summary['rmse_nm']:.2f} nm to {after_summary['rmse_nm']:.2f} nm "
        f"({100 * drop:.0f}% lower)."
    )
