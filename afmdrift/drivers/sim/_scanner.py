"""Raster timing and rendering of the simulated AFM.

Timing of one frame (``T_l = 1 / line_rate_hz``, ``f`` = trace fraction):
scan line ``k`` (0-based in scan order) starts at ``t_start + k T_l``; its
pixel ``j`` of ``N_c`` is measured at ``t_start + k T_l + (j + ½) f T_l / N_c``
(the trace), the rest of the line period is the retrace. An ``up`` frame scans
rows 0 → N_r−1, a ``down`` frame N_r−1 → 0. The frame ends at
``t_start + N_r T_l``.

Rendering: pixel (row ``r``, column ``j``) sits at image position
``u = (j Δx, r Δy)`` of the scan window. At its own time ``t`` the scanner
reads the sample at

    s = u + c(t) − p(t) − b_dir

where ``c`` is the commanded offset (plus the drift-compensation ramp, see
``DriftPhysics.scan_offset_at``), ``p`` the true drift (so a feature at
image position ``u`` at t = 0 appears at ``u + p(t)``), and ``b_dir`` the
scan-direction bias (``+b/2`` for up, ``−b/2`` for down frames). The height is
the sample's height at ``s`` plus the tilt plane, the slow z offset (per line),
a per-line offset and white detector noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from afmdrift.drivers.sim._models import SimPhysics
from afmdrift.drivers.sim._sample import Sample
from afmdrift.drivers.sim._scenario import ArtefactsConfig
from afmdrift.records import ScanDirection

__all__ = ["FrameRaster", "ScanGeometry", "render_lines"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class ScanGeometry:
    """Scan size, pixels and timing (all immutable; replaced on reconfiguration)."""

    size_nm: tuple[float, float]
    pixels: tuple[int, int]  # (cols, rows)
    line_rate_hz: float
    trace_fraction: float = 0.5
    min_frame_period_s: float = 0.0
    alternate: bool = True

    @property
    def pixel_size_nm(self) -> tuple[float, float]:
        """Pixel size (x, y) in nm: scan size divided by pixels."""
        return (self.size_nm[0] / self.pixels[0], self.size_nm[1] / self.pixels[1])

    @property
    def line_period_s(self) -> float:
        return 1.0 / self.line_rate_hz

    @property
    def scan_time_s(self) -> float:
        """Duration of one frame's scan, rows × line period."""
        return self.pixels[1] * self.line_period_s

    @property
    def frame_period_s(self) -> float:
        """Time between frame starts: the scan time, or the configured period if longer."""
        return max(self.scan_time_s, self.min_frame_period_s)


@dataclass(slots=True)
class FrameRaster:
    """A frame being scanned: its timing, buffer and per-frame random artefacts."""

    index: int
    geometry: ScanGeometry
    t_start_s: float
    direction: ScanDirection
    heights_nm: FloatArray
    noise_nm: npt.NDArray[np.floating]
    line_offsets_nm: FloatArray
    lines_done: int = 0

    @property
    def t_end_s(self) -> float:
        return self.t_start_s + self.geometry.scan_time_s

    def lines_due(self, t_s: float) -> int:
        """Number of scan lines whose trace has ended by ``t_s``."""
        g = self.geometry
        trace_end_0 = self.t_start_s + g.trace_fraction * g.line_period_s
        k = int(np.floor((t_s - trace_end_0) / g.line_period_s + 1e-9)) + 1
        return int(np.clip(k, 0, g.pixels[1]))

    def rows_of_lines(self, k0: int, k1: int) -> npt.NDArray[np.int64]:
        """Image rows of scan lines ``k0..k1-1``."""
        k = np.arange(k0, k1)
        if self.direction is ScanDirection.DOWN:
            k = self.geometry.pixels[1] - 1 - k
        return k

    def pixel_times(self, k0: int, k1: int) -> FloatArray:
        """Measurement time of every pixel of scan lines ``k0..k1-1``, shape (k1-k0, cols)."""
        g = self.geometry
        cols = g.pixels[0]
        line_start = self.t_start_s + np.arange(k0, k1) * g.line_period_s
        within = (np.arange(cols) + 0.5) / cols * g.trace_fraction * g.line_period_s
        out: FloatArray = line_start[:, None] + within[None, :]
        return out


def _window_per_pixel(
    physics: SimPhysics, t: FloatArray, jumps_s: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Window displacement ``w = c(t) + q(t) − p(t)`` for every pixel time ``t``
    (lines × cols); ``q`` is the drift-compensation ramp.

    Evaluated at the first and last pixel of each line and interpolated linearly
    in between (c is constant and p smooth on the scale of one trace), except on
    lines whose trace contains a jump (offset move, tip change), which are
    evaluated exactly. Returns ``(w_x, w_y)``, each of shape (lines, cols), nm.
    """
    ends_t = t[:, [0, -1]]
    w_ends = physics.scan_offset_at(ends_t) - physics.drift_at(ends_t)  # (lines, 2, 2)
    cols = t.shape[1]
    frac = np.arange(cols) / max(cols - 1, 1)
    out = []
    for axis in (0, 1):
        w0 = w_ends[:, 0, axis]
        out.append(w0[:, None] + (w_ends[:, 1, axis] - w0)[:, None] * frac[None, :])
    jumps_s = jumps_s[(jumps_s > t[0, 0]) & (jumps_s <= t[-1, -1])]
    if jumps_s.size:
        inside = (jumps_s[None, :] > t[:, :1]) & (jumps_s[None, :] <= t[:, -1:])
        for i in np.nonzero(inside.any(axis=1))[0]:
            exact = physics.scan_offset_at(t[i]) - physics.drift_at(t[i])
            out[0][i] = exact[:, 0]
            out[1][i] = exact[:, 1]
    return out[0], out[1]


def render_lines(
    frame: FrameRaster,
    k0: int,
    k1: int,
    *,
    physics: SimPhysics,
    sample: Sample,
    artefacts: ArtefactsConfig,
    bias_nm: tuple[float, float],
    jumps_s: FloatArray,
) -> None:
    """Scan lines ``k0..k1-1`` of ``frame`` into its height buffer.

    Parameters
    ----------
    frame : FrameRaster
    k0, k1 : int
        Scan-order line range.
    physics : SimPhysics
        Source of p(t), the commanded offset c(t) and the z offset.
    sample : Sample
    artefacts : ArtefactsConfig
    bias_nm : (float, float)
        Scan-direction bias ``b_dir`` for this frame's direction, nm.
    jumps_s : ndarray, shape (m,)
        Times at which p or c jump (moves, tip changes).
    """
    if k1 <= k0:
        return
    g = frame.geometry
    px, py = g.pixel_size_nm
    rows = frame.rows_of_lines(k0, k1)
    t = frame.pixel_times(k0, k1)
    wx, wy = _window_per_pixel(physics, t, jumps_s)
    sx = wx
    sx += np.arange(g.pixels[0])[None, :] * px - bias_nm[0]
    sy = wy
    sy += (rows * py - bias_nm[1])[:, None]
    h = sample.heights_at(sx, sy)
    tx, ty = artefacts.tilt
    if tx or ty:
        h += tx * sx + ty * sy
    t_mid = t[:, t.shape[1] // 2]
    h += physics.z_offset_nm(t_mid, rate_nm_per_s=artefacts.z_drift_nm_per_s)[:, None]
    h += frame.line_offsets_nm[rows][:, None]
    h += frame.noise_nm[rows]
    frame.heights_nm[rows] = h
    frame.lines_done = k1
