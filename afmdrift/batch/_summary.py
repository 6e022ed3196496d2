"""``OUT/summary.csv`` (one row per recording, rewritten atomically) and the
archive's picture next to it."""

from __future__ import annotations

import csv
import html
import io
import math
import os
from collections.abc import Sequence
from pathlib import Path

from afmdrift.batch._jobs import Result

__all__ = ["SUMMARY_COLUMNS", "plot_archive", "write_summary"]

#: Columns of ``summary.csv``, in order.
SUMMARY_COLUMNS: tuple[str, ...] = (
    "recording",
    "status",
    "frames",
    "valid_frames",
    "prior_decided",
    "drift_x_nm",
    "drift_y_nm",
    "worker",
    "seconds",
    "error",
)


def write_summary(path: Path, rows: Sequence[Result | None], recordings: Sequence[str]) -> None:
    """Rewrite ``path`` with one row per recording, in the order given; a recording
    not finished yet has an empty status. Atomic: a reader (or a run killed
    meanwhile) sees the old file or the new one, never half of one."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(SUMMARY_COLUMNS)
    for rec, r in zip(recordings, rows, strict=True):
        if r is None:
            w.writerow([rec] + [""] * (len(SUMMARY_COLUMNS) - 1))
            continue
        w.writerow(
            [
                rec,
                r.status,
                r.frames,
                r.valid_frames,
                r.prior_decided,
                _num(r.drift_x_nm),
                _num(r.drift_y_nm),
                r.worker,
                f"{r.seconds:.3f}",
                r.error,
            ]
        )
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(buf.getvalue(), encoding="utf-8")
    os.replace(tmp, path)


def _num(v: float) -> str:
    return repr(float(v)) if math.isfinite(v) else ""


#: The picture's geometry, in SVG user units (pixels at 100 %).
_WIDTH, _ROW, _TOP, _BOTTOM, _GAP = 1100.0, 16.0, 44.0, 44.0, 24.0
#: Axis ends: these times a power of ten.
_ROUND = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)
_DONE, _FAILED, _GRID, _FONT = "#1f77b4", "#d62728", "#d9d9d9", "DejaVu Sans, Arial, sans-serif"
_NO_DRIFT = "#7f7f7f"
#: What a recording's bars say instead of a drift, by status.
_MARKS = {"failed": "failed", "no_drift": "no drift measured"}


def plot_archive(path: Path, rows: Sequence[Result | None], stems: Sequence[str]) -> None:
    """The archive at a glance, as an SVG next to ``summary.csv``: per recording
    (one row each, in the order given), the drift rate (nm/min), the total
    drift (nm) and the share of valid frames, as horizontal bars; failed
    recordings in red. Each bar's tooltip gives its exact value.

    Written directly as text: a few milliseconds for any size of archive, where
    a plotting library took 0.3 s to import and 1.5 s to draw 300 recordings,
    on the command's serial path. Vector, so a 300-row archive stays sharp and
    its names searchable in a browser."""
    done = [(s, r) for s, r in zip(stems, rows, strict=True) if r is not None]
    # no drift (a failed recording, or one none of whose frames was measured)
    # is no bar, never a bar of zero
    total = [math.hypot(r.drift_x_nm, r.drift_y_nm) if r.status == "done" else math.nan
             for _, r in done]  # fmt: skip
    rate = [
        t / (r.duration_s / 60.0) if r.status == "done" and r.duration_s > 0 else math.nan
        for t, (_, r) in zip(total, done, strict=True)
    ]
    share = [r.valid_frames / r.frames if r.frames else 0.0 for _, r in done]
    failed = [r.status == "failed" for _, r in done]
    marks = [_MARKS.get(r.status, "") for _, r in done]
    label_w = min(14.0 + 7.2 * max((len(n) for n, _ in done), default=4), 0.4 * _WIDTH)
    panel_w = (_WIDTH - label_w - 10.0 - 2 * _GAP - 16.0) / 3
    height = _TOP + _ROW * max(len(done), 1) + _BOTTOM
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{_WIDTH:.0f}" height="{height:.0f}" '
        f'viewBox="0 0 {_WIDTH:.0f} {height:.0f}" font-family="{_FONT}" font-size="11">',
        '<rect width="100%" height="100%" fill="white"/>',
        f'<text x="{_WIDTH / 2:.1f}" y="18" text-anchor="middle" font-size="13">'
        f"{len(done)} recordings ({sum(failed)} failed, in red): "
        "drift since each one&#8217;s first frame</text>",
    ]
    for k, (name, _) in enumerate(done):
        y = _TOP + _ROW * (k + 0.5)
        out.append(f'<text x="{label_w:.1f}" y="{y + 4:.1f}" text-anchor="end">{_esc(name)}</text>')
    for i, (values, label, unit, top) in enumerate(
        (
            (rate, "drift rate (nm/min)", "nm/min", _nice(_finite_max(rate))),
            (total, "total drift (nm)", "nm", _nice(_finite_max(total))),
            (share, "valid frames (share)", "", 1.0),
        )
    ):
        x0 = label_w + 10.0 + i * (panel_w + _GAP)
        out.extend(_panel(x0, panel_w, len(done), values, marks, [n for n, _ in done],
                          label, unit, top))  # fmt: skip
    out.append("</svg>")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(out) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def _panel(
    x0: float,
    width: float,
    n: int,
    values: Sequence[float],
    marks: Sequence[str],
    names: Sequence[str],
    label: str,
    unit: str,
    top: float,
) -> list[str]:
    """One panel: its grid and tick labels, a bar per recording, the axis label."""
    y0, y1 = _TOP, _TOP + _ROW * max(n, 1)
    out = []
    for t in range(6):
        x = x0 + width * t / 5
        out.append(
            f'<line x1="{x:.1f}" y1="{y0:.1f}" x2="{x:.1f}" y2="{y1:.1f}" stroke="{_GRID}"/>'
        )
        out.append(f'<text x="{x:.1f}" y="{y1 + 14:.1f}" text-anchor="middle">'
                   f"{_tick(top * t / 5)}</text>")  # fmt: skip
    out.append(f'<text x="{x0 + width / 2:.1f}" y="{y1 + 32:.1f}" text-anchor="middle">'
               f"{label}</text>")  # fmt: skip
    for k, (v, mark, name) in enumerate(zip(values, marks, names, strict=True)):
        y = y0 + _ROW * k + 2
        w = width * min(max(v, 0.0) / top, 1.0) if top > 0 and math.isfinite(v) else 0.0
        shown = mark == "failed" or (bool(mark) and not math.isfinite(v))
        tip = f"{_esc(name)}: {mark}" if shown else f"{_esc(name)}: {v:.4g} {unit}".rstrip()
        colour = _FAILED if mark == "failed" else _NO_DRIFT if mark else _DONE
        out.append(f'<rect x="{x0:.1f}" y="{y:.1f}" width="{w:.1f}" height="{_ROW - 4:.0f}" '
                   f'fill="{colour}"><title>{tip}</title></rect>')  # fmt: skip
        if shown and unit == "nm":
            out.append(f'<text x="{x0 + 3:.1f}" y="{y + 9:.1f}" fill="{colour}" '
                       f'font-size="9">{mark}</text>')  # fmt: skip
    out.append(f'<line x1="{x0:.1f}" y1="{y0:.1f}" x2="{x0:.1f}" y2="{y1:.1f}" stroke="black"/>')
    return out


def _finite_max(values: Sequence[float]) -> float:
    return max((v for v in values if math.isfinite(v)), default=0.0)


def _nice(peak: float) -> float:
    """The axis end for values up to ``peak``: a round multiple of a power of ten."""
    if not math.isfinite(peak) or peak <= 0:
        return 1.0
    power = 10.0 ** math.floor(math.log10(peak))
    return next(m * power for m in _ROUND if m * power >= peak * (1 - 1e-12))


def _tick(v: float) -> str:
    return f"{v:.3g}"


def _esc(text: str) -> str:
    return html.escape(text, quote=True)
