"""Self-contained HTML report of a :class:`Diagnosis` (figures as inline PNG).

The page has no external resources: every figure is a matplotlib (Agg)
PNG embedded as a base64 ``data:`` URI, styles are inline. Figures:

1. measured vs predicted drift, x and y;
2. one-step errors with the failure episodes shaded;
3. autocorrelation and Lomb–Scargle periodogram of the errors;
4. cross-correlation of the errors with each logged channel's increments;
5. added-variable plot of the top candidate (and its ΔAICc profile over θ);
   when the leading candidate is a generic term (``channel:``, ``event:``),
   its driver over the one-step errors: the channel trace and its lagged
   version with the fitted τ, or a mark at each event of the kind;
6. the registration block vector field of the worst frame (against the
   frame before it), when the frames are available;
7. before/after one-step errors when a missing effect was found.
"""

from __future__ import annotations

import base64
import html
import io
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from afmdrift.diagnostics._data import RunData
from afmdrift.diagnostics._diagnosis import Diagnosis
from afmdrift.diagnostics._stats import cross_correlation, lomb_scargle
from afmdrift.diagnostics._text import cv_change
from afmdrift.errors import InputError
from afmdrift.session import read_session

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from afmdrift.config import RegistrationConfig

__all__ = ["write_report"]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

_CSS = """
body { font-family: sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
h1 { font-size: 1.6em; } h2 { font-size: 1.25em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: 0.6em 0; }
td, th { border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }
th { background: #eee; } td.l, th.l { text-align: left; }
.finding { background: #f4f8ff; border-left: 4px solid #3a6fd8; padding: 0.6em 1em; }
pre { background: #f6f6f6; padding: 0.6em; }
img { max-width: 100%; display: block; margin: 0.4em 0; }
"""


#: Marks how many figures the browser decoded (read by the headless-browser test).
_FIGURE_CHECK = (
    "<script>window.addEventListener('load',function(){"
    "var imgs=document.querySelectorAll('img.figure');var ok=0;"
    "imgs.forEach(function(i){if(i.complete&&i.naturalWidth>0){ok++;}});"
    "var m=document.createElement('div');m.id='figure-check';"
    "m.setAttribute('data-total',imgs.length);m.setAttribute('data-rendered',ok);"
    "document.body.appendChild(m);});</script>"
)


def _png(fig: Figure) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _img(fig: Figure, alt: str) -> str:
    return f'<img class="figure" alt="{html.escape(alt)}" src="data:image/png;base64,{_png(fig)}">'


def _h(s: object) -> str:
    return html.escape(str(s))


def _fmt(v: Any, spec: str = ".2f") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, str):
        return v
    return format(v, spec)


def _fig_compare(dg: Diagnosis) -> Figure:
    import matplotlib.pyplot as plt

    run = dg.run
    fig, axes = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True)
    t_h = run.t_s / 3600.0
    for a, ax in enumerate(axes):
        ax.plot(t_h, run.measured_nm[:, a], "o", ms=3, label="measured p")
        ax.plot(t_h, run.predicted_nm[:, a], "-", lw=1, label="one-step prediction")
        if dg.after is not None:
            ax.plot(t_h, dg.after.predicted_nm[:, a], "-", lw=1, label="with the added effect")
        ax.set_ylabel(f"{'xy'[a]} (nm)")
        ax.legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time (h)")
    fig.suptitle("Measured vs predicted drift")
    return fig


def _fig_residuals(dg: Diagnosis) -> Figure:
    import matplotlib.pyplot as plt

    run = dg.run
    fig, axes = plt.subplots(2, 1, figsize=(10, 5), sharex=True)
    t_h = run.t_s / 3600.0
    step_h = float(np.median(np.diff(t_h))) if t_h.size > 1 else 0.1
    for a, ax in enumerate(axes):
        ax.axhline(0, color="k", lw=0.5)
        ax.plot(t_h, run.errors_nm[:, a], ".-", lw=0.8, ms=4, label="one-step error")
        for f in dg.failures:
            ax.axvspan(
                f.t_start_s / 3600.0 - step_h / 2,
                f.t_end_s / 3600.0 + step_h / 2,
                color="tab:red" if f.kind == "outlier" else "tab:orange",
                alpha=0.25,
            )
        if dg.burn_in_frames and t_h.size > dg.burn_in_frames:
            ax.axvspan(t_h[0], t_h[dg.burn_in_frames], color="0.85", alpha=0.5, label="burn-in")
        _mark_discovered(ax, dg, a)
        ax.set_ylabel(f"e_{'xy'[a]} (nm)")
        ax.legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time (h)")
    fig.suptitle("One-step errors (red: outliers, orange: sustained bias)")
    return fig


def _mark_discovered(ax: Any, dg: Diagnosis, axis: int) -> None:
    """The significant drift shapes read from the drift itself, on one axis of
    the error plot: a jump or a change of rate as a line at its time, a cycle
    as its fitted sinusoid (level, nm) over the record."""
    run = dg.run
    for c in dg.candidates:
        if not c.significant or c.discovered is None:
            continue
        d = c.discovered
        kind = d.get("kind")
        where = d.get("period_s", d.get("t_s"))
        if not isinstance(where, int | float):
            continue
        if kind == "periodic":
            period = float(where)
            a = c.params.get(f"sin_nm_{'xy'[axis]}", math.nan)
            b = c.params.get(f"cos_nm_{'xy'[axis]}", math.nan)
            if not (math.isfinite(a) and math.isfinite(b)):
                continue
            t = np.linspace(float(run.t_s[0]), float(run.t_s[-1]), 800)
            phase = 2.0 * np.pi * t / period
            label = f"discovered cycle ({period / 60:.0f} min)"
            wave = a * np.sin(phase) + b * np.cos(phase)
            ax.plot(t / 3600.0, wave, "-", color="tab:green", lw=1.2, alpha=0.8, label=label)
        else:
            t_h = float(where) / 3600.0
            what = "discovered jump" if kind == "jump" else "discovered change of rate"
            ax.axvline(t_h, color="tab:purple", lw=1.5, ls="--", label=what)


def _fig_acf_periodogram(dg: Diagnosis) -> Figure:
    import matplotlib.pyplot as plt
    from statsmodels.tsa.stattools import acf

    run = dg.run
    b = dg.burn_in_frames
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for a in (0, 1):
        e = run.errors_nm[b:, a]
        e = e[np.isfinite(e)]
        if e.size >= 8 and np.std(e) > 0:
            nl = min(20, e.size // 2)
            r = acf(e, nlags=nl, fft=True)
            axes[0].plot(np.arange(nl + 1) + (0.1 * a), r, "o-", ms=3, label="xy"[a])
            period, power = lomb_scargle(run.t_s[b:], run.errors_nm[b:, a])
            if power.size:
                axes[1].semilogx(period / 3600.0, power, label="xy"[a])
    n = max(int(np.isfinite(run.errors_nm[b:, 0]).sum()), 1)
    band = 1.96 / math.sqrt(n)
    axes[0].axhspan(-band, band, color="0.85")
    axes[0].set_xlabel("lag (frames)")
    axes[0].set_ylabel("autocorrelation")
    axes[0].legend(fontsize=8)
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    axes[1].xaxis.set_major_formatter(ScalarFormatter())
    axes[1].xaxis.set_minor_formatter(NullFormatter())
    axes[1].set_xlabel("period (h)")
    axes[1].set_ylabel("normalised power")
    axes[1].legend(fontsize=8)
    fig.suptitle("Autocorrelation and periodogram of the one-step errors")
    return fig


def _fig_xcorr(dg: Diagnosis, data: RunData) -> Figure | None:
    import matplotlib.pyplot as plt

    names = data.channel_names()
    if not names:
        return None
    run = dg.run
    b = dg.burn_in_frames
    fig, axes = plt.subplots(1, len(names), figsize=(5 * len(names), 3.4), squeeze=False)
    max_lag = min(10, max(run.t_s.size // 5, 1))
    for i, name in enumerate(names):
        ax = axes[0, i]
        ct, cv = data.channel_series(name)
        if ct.size < 2:
            continue
        x = np.interp(run.t_s, ct, cv)
        dx = np.concatenate([[np.nan], np.diff(x)])
        for a in (0, 1):
            lags, r = cross_correlation(run.errors_nm[b:, a], dx[b:], max_lag=max_lag)
            ax.plot(lags, r, "o-", ms=3, label=f"e_{'xy'[a]}")
        n = max(run.t_s.size - b, 1)
        ax.axhspan(-1.96 / math.sqrt(n), 1.96 / math.sqrt(n), color="0.85")
        ax.set_title(f"Δ{name}", fontsize=9)
        ax.set_xlabel("lag (frames; + = error follows channel)")
        ax.set_ylabel("correlation")
        ax.legend(fontsize=8)
    fig.suptitle("Cross-correlation of errors with logged channel increments")
    return fig


def _fig_added_variable(dg: Diagnosis) -> Figure | None:
    import matplotlib.pyplot as plt

    c = next((c for c in dg.candidates if c.testable and c.av), None)
    if c is None:
        return None
    ncols = 3 if c.profile else 2
    fig, axes = plt.subplots(1, ncols, figsize=(4.2 * ncols, 3.6))
    for a in (0, 1):
        xcol, ycol = c.av[a]
        ax = axes[a]
        ax.plot(xcol, ycol, ".", ms=4)
        if np.ptp(xcol) > 0:
            slope = float(xcol @ ycol / (xcol @ xcol))
            xs = np.linspace(xcol.min(), xcol.max(), 2)
            ax.plot(xs, slope * xs, "r-", lw=1, label=f"slope {slope:.3g}")
            ax.legend(fontsize=8)
        ax.set_xlabel(f"{c.effect} basis | model (quasi-differenced)")
        ax.set_ylabel(f"{'xy'[a]} residual | model (nm)")
    if c.profile:
        ax = axes[2]
        th = np.array([p[0] for p in c.profile])
        d = np.array([p[1] for p in c.profile])
        ax.semilogx(th, d, "o-", ms=3)
        ax.axhline(dg.thresholds.min_delta_aicc, color="r", lw=0.8, ls="--")
        ax.set_xlabel(next(iter(c.nonlinear.keys()), "θ"))
        ax.set_ylabel("ΔAICc")
    fig.suptitle(f"Added-variable plot of the top candidate: {c.effect}")
    return fig


def _fig_before_after(dg: Diagnosis) -> Figure | None:
    import matplotlib.pyplot as plt

    if dg.after is None:
        return None
    fig, ax = plt.subplots(figsize=(10, 3.4))
    t_h = dg.run.t_s / 3600.0
    e0 = np.hypot(dg.run.errors_nm[:, 0], dg.run.errors_nm[:, 1])
    e1 = np.hypot(dg.after.errors_nm[:, 0], dg.after.errors_nm[:, 1])
    ax.plot(t_h, e0, ".-", lw=0.8, label=f"before: {', '.join(dg.model_effects)}")
    ax.plot(t_h, e1, ".-", lw=0.8, label=f"after: {', '.join(dg.after.effects)}")
    ax.set_xlabel("time (h)")
    ax.set_ylabel("|one-step error| (nm)")
    ax.legend(fontsize=8)
    fig.suptitle("Before and after adding the effect")
    return fig


def _frame_images(
    data: RunData, seq: int
) -> tuple[npt.NDArray[np.floating], npt.NDArray[np.floating]] | None:
    """Images of frame ``seq`` and the one before it (session or frame archive)."""
    if seq < 1:
        return None
    if data.run_dir is not None:
        a = data.run_dir / "frames" / f"{seq - 1:06d}.npy"
        b = data.run_dir / "frames" / f"{seq:06d}.npy"
        if a.is_file() and b.is_file():
            return np.load(a), np.load(b)
    if data.session_dir is not None:
        s = read_session(data.session_dir)
        if seq < len(s):
            return np.asarray(s.frames[seq - 1]), np.asarray(s.frames[seq])
    return None


def _fig_vector_field(
    dg: Diagnosis, data: RunData, registration: RegistrationConfig | None
) -> tuple[Figure | None, str]:
    import matplotlib.pyplot as plt

    from afmdrift.registration import measure_drift

    norm = np.hypot(dg.run.errors_nm[:, 0], dg.run.errors_nm[:, 1])
    if not np.isfinite(norm).any():
        return None, "no one-step error to rank the frames by"
    k = int(np.nanargmax(norm))
    seq = int(dg.run.frames[k])
    images = _frame_images(data, seq)
    if images is None:
        return None, (
            f"frame {seq} has the largest error ({norm[k]:.2f} nm); its image is not "
            "available (pass --session, or record the run with archive_frames = true)"
        )
    try:
        res = measure_drift(
            images[0], images[1], pixel_size_nm=data.pixel_size_nm, config=registration
        )
    except (InputError, ValueError) as err:
        return None, f"frame {seq}: registration against frame {seq - 1} failed: {err}"
    fld = res.field
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.imshow(np.asarray(images[1]), cmap="gray", origin="upper")
    c = np.asarray(fld.centres_px, dtype=np.float64)
    v = np.asarray(fld.vectors_px, dtype=np.float64)
    valid = np.asarray(fld.valid, dtype=bool)
    scale = 4.0
    for sel, colour, label in ((valid, "lime", "kept"), (~valid, "red", "rejected")):
        if sel.any():
            ax.quiver(
                c[sel, 0],
                c[sel, 1],
                scale * v[sel, 0],
                scale * v[sel, 1],
                color=colour,
                angles="xy",
                scale_units="xy",
                scale=1.0,
                label=label,
            )
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title(
        f"Frame {seq} vs frame {seq - 1}: block vectors ×{scale:g} "
        f"(mean {res.dx_nm:.2f}, {res.dy_nm:.2f} nm)",
        fontsize=9,
    )
    return fig, (
        f"frame {seq} at t = {dg.run.t_s[k]:.0f} s has the largest one-step error "
        f"({norm[k]:.2f} nm); {int(valid.sum())} of {valid.size} blocks kept"
    )


def _table(header: list[str], rows: list[list[str]], left: int = 1) -> str:
    th = "".join(
        f'<th class="l">{_h(h)}</th>' if i < left else f"<th>{_h(h)}</th>"
        for i, h in enumerate(header)
    )
    body = "".join(
        "<tr>"
        + "".join(
            f'<td class="l">{_h(c)}</td>' if i < left else f"<td>{_h(c)}</td>"
            for i, c in enumerate(r)
        )
        + "</tr>"
        for r in rows
    )
    return f"<table><tr>{th}</tr>{body}</table>"


def render_report(
    dg: Diagnosis, data: RunData, *, registration: RegistrationConfig | None = None
) -> str:
    """The report as one HTML string."""
    import matplotlib

    matplotlib.use("Agg")
    j = dg.to_json()
    parts = [
        *_header(dg, j),
        *_compare_section(dg, j),
        *_failures_section(dg, data, j),
        *_candidates_section(dg, j),
        *_after_section(dg, j),
        *_worst_frame_section(dg, data, registration),
        _FIGURE_CHECK,
        "</body></html>",
    ]
    return "".join(parts)


def _header(dg: Diagnosis, j: dict[str, Any]) -> list[str]:
    """Document head, title, the model in one line and the finding box with its snippet."""
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<title>afmdrift diagnose</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>Model against measurement</h1>",
        f"<p>Model: <b>{_h(', '.join(dg.model_effects))}</b> "
        f"(active: {_h(', '.join(dg.active_effects))}); {j['frames']} fed frames, the first "
        f"{j['burn_in_frames']} left out of the statistics.</p>",
        f'<div class="finding" id="finding"><p><b>{_h(dg.plain)}</b></p><p>{_h(dg.finding)}</p>',
    ]
    snippet = dg.config_snippet()
    if snippet:
        parts.append(f"<pre>{_h(snippet)}</pre>")
    parts.append("</div>")
    return parts


def _compare_section(dg: Diagnosis, j: dict[str, Any]) -> list[str]:
    """Section 1: one-step (and continuous-vs-truth) error table, measured vs predicted."""
    rows = [
        [
            "one-step",
            _fmt(j["rmse_nm"]),
            _fmt(j["rmse_x_nm"]),
            _fmt(j["rmse_y_nm"]),
            _fmt(j["mean_abs_error_nm"]),
            _fmt(j["peak_error_nm"]),
        ]
    ]
    if j["truth"] is not None:
        t = j["truth"]
        rows.append(
            [
                "continuous vs truth",
                _fmt(t["rmse_nm"]),
                "–",
                "–",
                _fmt(t["mean_abs_error_nm"]),
                _fmt(t["peak_error_nm"]),
            ]
        )
    return [
        "<h2>1. Compare</h2>",
        _table(["error (nm)", "RMS", "RMS x", "RMS y", "mean |e|", "peak"], rows),
        _img(_fig_compare(dg), "measured vs predicted"),
    ]


def _failures_section(dg: Diagnosis, data: RunData, j: dict[str, Any]) -> list[str]:
    """Section 2: errors with episodes, episode table, patterns, whiteness, channels."""
    parts = ["<h2>2. Where it fails</h2>"]
    parts.append(_img(_fig_residuals(dg), "one-step errors with failure episodes"))
    if dg.failures:
        parts.append(
            _table(
                ["from (s)", "to (s)", "kind", "peak (nm)", "what was happening"],
                [
                    [
                        f"{f.t_start_s:.0f}",
                        f"{f.t_end_s:.0f}",
                        f.kind,
                        _fmt(f.peak_error_nm),
                        f.note,
                    ]
                    for f in dg.failures
                ],
                left=0,
            )
        )
    else:
        parts.append("<p>No failure episode found.</p>")
    if dg.patterns:
        parts.append("<ul>" + "".join(f"<li>{_h(p)}</li>" for p in dg.patterns) + "</ul>")
    parts.append(_whiteness_table(j))
    if j["up_down"] is not None:
        u = j["up_down"]
        parts.append(
            f"<p>Up minus down frames: x {_fmt(u['diff_x_nm'])} nm, y {_fmt(u['diff_y_nm'])} "
            f"nm (Welch p = {_fmt(u['p_value'], '.2g')}).</p>"
        )
    parts.append(_img(_fig_acf_periodogram(dg), "autocorrelation and periodogram"))
    xc = _fig_xcorr(dg, data)
    if xc is not None:
        parts.append(_img(xc, "cross-correlation with channels"))
    return parts


def _whiteness_table(j: dict[str, Any]) -> str:
    """Ljung–Box Q and p-value, periodogram peak period and power, per axis."""
    lb = j["ljung_box"]
    pg = j["periodogram"]
    return _table(
        ["axis", "Ljung–Box Q", "p-value", "peak period (s)", "peak power"],
        [
            [
                a,
                _fmt(lb[a]["q"], ".1f"),
                _fmt(lb[a]["p_value"], ".2g"),
                _fmt(pg[a]["peak_period_s"], ".0f"),
                _fmt(pg[a]["peak_power"], ".2f"),
            ]
            for a in ("x", "y")
        ],
    )


def _candidates_section(dg: Diagnosis, j: dict[str, Any]) -> list[str]:
    """Section 3: the candidate table and the top candidate's added-variable plot."""
    parts = ["<h2>3. Which effect is missing</h2>"]
    parts.append(
        _table(
            [
                "effect",
                "significant",
                "ΔAICc",
                "HAC p (Bonf.)",
                "CV error",
                "RMS with it (nm)",
                "params",
            ],
            [_candidate_row(c) for c in j["candidates"]],
        )
    )
    av = _fig_added_variable(dg)
    if av is not None:
        parts.append(_img(av, "added-variable plot"))
    drv = _fig_driver(dg)
    if drv is not None:
        parts.append(_img(drv, "driver of the leading generic candidate over the errors"))
    return parts


def _fig_driver(dg: Diagnosis) -> Figure | None:
    """The driver of the leading generic candidate over the one-step errors.

    A channel: its logged trace (right axis) and, over the errors, the
    frame-to-frame change of the fitted response g·ΔC_s (the fitted lag and
    gain): what the term would have predicted of each error. An event kind:
    a vertical mark at each event. None when no testable generic candidate
    exists (a drift shape read from the drift has no driver: the error plot
    marks it, :func:`_mark_discovered`).
    """
    import matplotlib.pyplot as plt

    from afmdrift.model import available_terms, term_class

    c = next(
        (c for c in dg.candidates if c.testable and c.driver and "drift_shape" not in c.driver),
        None,
    )
    if c is None:
        return None
    run = dg.run
    t_h = run.t_s / 3600.0
    fig, axes = plt.subplots(2, 1, figsize=(10, 5), sharex=True)
    for a, ax in enumerate(axes):
        ax.axhline(0, color="k", lw=0.5)
        ax.plot(t_h, run.errors_nm[:, a], ".-", lw=0.8, ms=4, color="tab:blue")
        ax.set_ylabel(f"e_{'xy'[a]} (nm)", color="tab:blue")
        if "channel" in c.driver:
            name = c.driver["channel"]
            hist = run.history
            tt = np.asarray(hist.channel_t_s, dtype=np.float64)
            right = ax.twinx()
            right.plot(tt / 3600.0, hist.channel_at(name, tt), color="tab:orange", lw=0.6)
            right.set_ylabel(f"{name} (orange)", fontsize=8, color="tab:orange")
            term = term_class(c.effect, available_terms(run.predictor.config.plugins))()
            gain = c.params.get(f"{term.coefficient_units[0]}_{'xy'[a]}", math.nan)
            if math.isfinite(gain):
                lagged = term.design(
                    run.t_s, hist, scan_sign=run.scan_sign, params=c.nonlinear, axis=a
                )[:, 0]
                step = np.concatenate([[np.nan], np.diff(lagged)]) * gain
                ax.plot(t_h, step, color="tab:red", lw=1.2, label="fitted g·ΔC_s per frame")
                ax.legend(loc="best", fontsize=8)
        else:
            kind = c.driver["event_kind"]
            for e in run.history.events:
                if str(e.kind) == kind:
                    ax.axvline(e.t_s / 3600.0, color="tab:red", lw=1, alpha=0.7)
    axes[-1].set_xlabel("time (h)")
    what = (
        f"channel {c.driver['channel']}"
        if "channel" in c.driver
        else f"{c.driver['event_kind']} events (red marks)"
    )
    fig.suptitle(f"One-step errors and the driver of {c.effect}: {what}")
    return fig


def _candidate_row(c: dict[str, Any]) -> list[str]:
    """One row of the candidate table, from the candidate's JSON object."""
    return [
        c["effect"],
        "yes" if c["significant"] else ("no" if c["testable"] else "not testable"),
        _fmt(c["delta_aicc"], ".1f"),
        _fmt(c["p_bonferroni"], ".2g"),
        cv_change(c).replace("-", "–") if c["cv_drop"] is None else cv_change(c),
        _fmt(c["rmse_after_nm"]) + (" (est.)" if c["rmse_after_kind"] == "cv_estimate" else ""),
        ", ".join(f"{k} = {_fmt(v, '.3g')}" for k, v in c["params"].items()) or (c["reason"] or ""),
    ]


def _after_section(dg: Diagnosis, j: dict[str, Any]) -> list[str]:
    """Section 4: errors before and after adding the found effect (table and figure)."""
    parts = ["<h2>4. Add it and watch the error fall</h2>"]
    if j["after"] is None:
        parts.append("<p>Nothing to add: no significant missing effect.</p>")
        return parts
    a = j["after"]
    parts.append(
        _table(
            ["model", "RMS (nm)", "mean |e| (nm)", "peak (nm)"],
            [
                [
                    "before: " + ", ".join(j["model_effects"]),
                    _fmt(j["rmse_nm"]),
                    _fmt(j["mean_abs_error_nm"]),
                    _fmt(j["peak_error_nm"]),
                ],
                [
                    "after: " + ", ".join(a["effects"]),
                    _fmt(a["rmse_nm"]),
                    _fmt(a["mean_abs_error_nm"]),
                    _fmt(a["peak_error_nm"]),
                ],
            ],
        )
    )
    ba = _fig_before_after(dg)
    if ba is not None:
        parts.append(_img(ba, "before and after"))
    return parts


def _worst_frame_section(
    dg: Diagnosis, data: RunData, registration: RegistrationConfig | None
) -> list[str]:
    """Section 5: a note on the worst frame and its block vector field, if available."""
    parts = ["<h2>5. The worst frame</h2>"]
    vf, note = _fig_vector_field(dg, data, registration)
    parts.append(f"<p>{_h(note)}</p>")
    if vf is not None:
        parts.append(_img(vf, "vector field of the worst frame"))
    return parts


def write_report(
    dg: Diagnosis,
    data: RunData,
    path: str | Path,
    *,
    registration: RegistrationConfig | None = None,
) -> Path:
    """Write the self-contained HTML report to ``path``.

    Raises
    ------
    InputError
        If the file cannot be written.
    """
    out = Path(path)
    text = render_report(dg, data, registration=registration)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text, encoding="utf-8")
    except OSError as err:
        raise InputError(f"{out}: cannot write the report: {err.strerror}") from None
    return out
