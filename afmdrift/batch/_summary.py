"""``OUT/summary.csv`` (one row per recording, rewritten atomically) and the
archive's picture next to it."""

from __future__ import annotations

import csv
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
            w.writerow([rec, "", "", "", "", "", "", "", ""])
            continue
        w.writerow(
            [
                rec,
                r.status,
                r.frames,
                r.valid_frames,
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


def import_plotting() -> None:
    """Import what :func:`plot_archive` draws with (0.3 s): a batch does it in a
    thread while the cluster works, not after the last recording."""
    import matplotlib.backends.backend_agg
    import matplotlib.figure  # noqa: F401


def plot_archive(path: Path, rows: Sequence[Result | None], stems: Sequence[str]) -> None:
    """Drift rate, total drift and valid share per recording (horizontal bars)."""
    # The object API with the Agg canvas, not pyplot: no global figure state in
    # a library call, and 0.1 s less import on the client's serial path.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    done = [(s, r) for s, r in zip(stems, rows, strict=True) if r is not None]
    names = [s for s, _ in done]
    total = [math.hypot(r.drift_x_nm, r.drift_y_nm) if r.status == "done" else 0.0
             for _, r in done]  # fmt: skip
    rate = [
        t / (r.duration_s / 60.0) if r.status == "done" and r.duration_s > 0 else 0.0
        for t, (_, r) in zip(total, done, strict=True)
    ]
    share = [r.valid_frames / r.frames if r.frames else 0.0 for _, r in done]
    height = max(2.5, 0.28 * len(names) + 1.2)
    fig = Figure(figsize=(11, height))
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3, sharey=True)
    colours = ["tab:blue" if r.status == "done" else "tab:red" for _, r in done]
    for ax, values, label in (
        (axes[0], rate, "drift rate (nm/min)"),
        (axes[1], total, "total drift (nm)"),
        (axes[2], share, "valid frames (share)"),
    ):
        ax.barh(range(len(names)), values, color=colours)
        ax.set_xlabel(label)
        ax.grid(axis="x", alpha=0.3)
    for i, (_, r) in enumerate(done):
        if r.status == "failed":
            axes[1].text(0, i, " failed", color="tab:red", va="center", fontsize=7)
    axes[0].set_yticks(range(len(names)), names, fontsize=7)
    axes[0].invert_yaxis()
    axes[2].set_xlim(0, 1)
    failed = sum(r.status == "failed" for _, r in done)
    fig.suptitle(
        f"{len(done)} recordings ({failed} failed, in red): drift since each one's first frame",
        fontsize=9,
    )
    # Margins from the sizes of the labels, in inches (tight_layout measures
    # every label by drawing it: seconds on an archive of hundreds).
    label_in = 0.3 + 0.055 * max((len(n) for n in names), default=1)
    fig.subplots_adjust(
        left=min(label_in / 11.0, 0.45),
        right=0.98,
        top=1.0 - 0.45 / height,
        bottom=0.55 / height,
        wspace=0.08,
    )
    fig.savefig(path, dpi=100)
