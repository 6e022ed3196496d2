"""The diagnosis as ``afmdrift diagnose`` prints it (without ``--json``).

The text is made from the JSON object (:meth:`Diagnosis.to_json`,
``docs/diagnostics.md``), so what a terminal shows and what a script reads
cannot disagree; ``afmdrift batch --task diagnose`` writes the same text next
to the object.
"""

from __future__ import annotations

from typing import Any

from afmdrift.diagnostics._candidates import cv_unstable

__all__ = ["GLOSSES", "cv_change", "diagnosis_text"]


def _f(v: Any, fmt: str = ".2f") -> str:
    return "-" if v is None else format(v, fmt)


#: The statistics the text names, each with the one line that says what it
#: means, printed under the first line that names it.
GLOSSES: tuple[tuple[str, str], ...] = (
    ("one-step error", "how far each frame's position was from the model's prediction made "
     "just before it"),
    ("Ljung-Box", "tests whether the errors are independent from frame to frame; a small p "
     "means something systematic is left in them"),
    ("ΔAICc", "how much better the model fits with the term, after a penalty per added "
     "parameter; above 10 is strong support"),
    ("cross-validated", "the error on stretches of the record left out of the fit, with the "
     "term against without it (negative: lower with it)"),
    ("HAC Wald", "the chance of so large a fitted term if the effect were absent, with "
     "errors that follow each other"),
    ("Bonferroni", "that chance multiplied by the number of tests tried, so that searching "
     "many effects, times and periods does not find one by luck"),
    ("Diebold-Mariano", "whether the model with the term predicts the next frame better "
     "than without it, frame by frame, more than by chance"),
)  # fmt: skip


def _glossed(lines: list[str], *, plain: int) -> list[str]:
    """``lines`` with the gloss of each statistic under the first line naming it
    (the first ``plain`` lines, the plain paragraph, are left as they are)."""
    out: list[str] = list(lines[:plain])
    seen: set[str] = set()
    for line in lines[plain:]:
        out.append(line)
        for word, gloss in GLOSSES:
            if word not in seen and word in line:
                seen.add(word)
                out.append(f"    ({word}: {gloss})")
    return out


def cv_change(c: dict[str, Any]) -> str:
    """The change of the cross-validated error in per cent, or what it is when
    a per cent means nothing: ``unstable`` when the term's out-of-sample error
    is more than :data:`~afmdrift.diagnostics._candidates.MAX_CV_RATIO` times
    the model's (a fit that blows up out of sample, :func:`cv_unstable`),
    ``-`` when it could not be cross-validated."""
    if c["cv_drop"] is None:
        return "-"
    if cv_unstable(c["cv_drop"]):
        return "unstable"
    return f"{-100 * c['cv_drop']:+.0f}%"


def diagnosis_text(j: dict[str, Any]) -> str:
    """What ``afmdrift diagnose`` prints: the JSON object of
    :meth:`Diagnosis.to_json` as a summary for the terminal. It opens with the
    finding in two plain sentences; the numbers follow, each statistic glossed
    in one line where it first appears."""
    lines = [
        j.get("plain_finding") or "",
        "",
        f"model: {', '.join(j['model_effects'])} "
        f"(active: {', '.join(j['active_effects']) or 'none'})",
        f"frames: {j['frames']} fed, first {j['burn_in_frames']} left out of the statistics",
        f"one-step error: RMS {_f(j['rmse_nm'])} nm (x {_f(j['rmse_x_nm'])}, "
        f"y {_f(j['rmse_y_nm'])}), mean |e| {_f(j['mean_abs_error_nm'])} nm, "
        f"peak {_f(j['peak_error_nm'])} nm",
    ]
    if j["truth"] is not None:
        t = j["truth"]
        lines.append(
            f"continuous prediction vs true drift: RMS {_f(t['rmse_nm'])} nm, "
            f"mean |e| {_f(t['mean_abs_error_nm'])} nm, peak {_f(t['peak_error_nm'])} nm"
        )
    lb = j["ljung_box"]
    lines.append(
        "Ljung-Box whiteness p-value: "
        + ", ".join(f"{a} {_f(lb[a]['p_value'], '.2g')}" for a in ("x", "y"))
    )
    for pat in j["patterns"]:
        lines.append(f"pattern: {pat}")
    if j["failures"]:
        lines.append("where it fails:")
        for f in j["failures"]:
            lines.append(f"  {f['t_start_s']:8.0f}-{f['t_end_s']:.0f} s  {f['note']}")
    else:
        lines.append("where it fails: no failure episode found")
    lines.append(
        "candidates (rank, effect, significant, ΔAICc, change of the cross-validated "
        "error, one-step RMS with it):"
    )
    width = max([15, *(len(c["effect"]) for c in j["candidates"])])
    for c in j["candidates"]:
        if not c["testable"]:
            lines.append(f"  {c['rank']:2d}. {c['effect']:<{width}} not testable: {c['reason']}")
            continue
        cv = cv_change(c)
        kind = "" if c["rmse_after_kind"] != "cv_estimate" else " (est.)"
        lines.append(
            f"  {c['rank']:2d}. {c['effect']:<{width}} {'YES' if c['significant'] else 'no ':<4} "
            f"{_f(c['delta_aicc'], '8.1f')} {cv:>7} "
            f"{'-' if c['rmse_after_nm'] is None else _f(c['rmse_after_nm']) + ' nm'}{kind}"
        )
    lines.append("")
    lines.append(j["finding"])
    if j["after"] is not None:
        a = j["after"]
        lines.append("")
        lines.append("before / after (one-step error, nm):")
        lines.append(f"  {'':<8}{'RMS':>8}{'mean|e|':>9}{'peak':>8}  effects")
        lines.append(
            f"  {'before':<8}{_f(j['rmse_nm'], '8.2f')}{_f(j['mean_abs_error_nm'], '9.2f')}"
            f"{_f(j['peak_error_nm'], '8.2f')}  {', '.join(j['model_effects'])}"
        )
        lines.append(
            f"  {'after':<8}{_f(a['rmse_nm'], '8.2f')}{_f(a['mean_abs_error_nm'], '9.2f')}"
            f"{_f(a['peak_error_nm'], '8.2f')}  {', '.join(a['effects'])}"
        )
    if j["config"]:
        lines.append("")
        lines.append(j["config"])
    return "\n".join(_glossed(lines, plain=2))
