"""A second session generator for tracks, different on purpose from the simulator.

A track (``afmdrift measure STACK``, ``batch``, ``replay``) must be right on
frames that afmdrift's own simulator (:mod:`afmdrift.drivers.sim`) did not
make. This generator differs from it in every part that registration sees:

* **Samples**: a Gaussian rough surface, graphite-like terraces or scattered
  particles of :mod:`afmdrift.testing` (the simulator renders gold on mica or
  a texture file), on a frame of 1 µm at any pixel count.
* **Frames**: rigid, every line at the shift of the frame's mid-scan time
  (the simulator renders every pixel at its own time), cut from an exactly
  shifted periodic texture (:class:`~afmdrift.testing.TextureShifter`), with
  white height noise; a frame every 240 s, scanned in 120 s, always upward.
* **Drift**: a settling exponential (a warm-up of 30–90 min, 50–200 nm), a
  slow sinusoid (period 1–3 h, 10–40 nm) and a random walk, each axis its
  own; the simulator builds drift from its library of physical effects.
* **Offset moves** (optional): three commanded moves of 40–160 nm per axis
  at random times between frames, logged as ``offset_move`` events; a move
  of +Δ moves the content by −Δ.

:attr:`GeneratedTrack.truth` is the drift p(t); :attr:`GeneratedTrack.image_px`
is what registration should find, the image position of each frame relative
to frame 0 (content at u in frame 0 is at u + m in frame k).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from afmdrift.records import Event, EventKind
from afmdrift.testing._images import (
    TextureShifter,
    add_noise,
    particle_texture,
    rough_texture,
    terrace_texture,
)

__all__ = ["TRACK_SAMPLES", "GeneratedTrack", "generate_track"]

FloatArray = npt.NDArray[np.float64]

Sample = Literal["rough", "terraces", "particles"]
#: The samples :func:`generate_track` draws.
TRACK_SAMPLES: tuple[Sample, ...] = ("rough", "terraces", "particles")

#: Frame edge, nm (the pixel count sets the pixel size).
FRAME_NM = 1024.0
FRAME_PERIOD_S = 240.0
SCAN_S = 120.0


@dataclass(frozen=True, slots=True)
class GeneratedTrack:
    """A generated session (the parts of a format-v1 session: every frame is
    scanned upward) and what registration should find in it."""

    #: Heights, nm, shape (N, rows, cols).
    frames: npt.NDArray[np.float32]
    #: ``(t_start_s, t_end_s)`` per frame, shape (N, 2).
    frame_times: FloatArray
    pixel_size_nm: tuple[float, float]
    line_time_s: float
    #: The commanded offset moves (``offset_move`` events).
    events: list[Event]
    #: Drift p(t): ``(t_s, x_nm, y_nm)`` at each frame's mid-scan time, shape (N, 3).
    truth: FloatArray
    #: Image position m of each frame relative to frame 0, px, shape (N, 2).
    image_px: FloatArray
    sample: str
    source: str


def _drift_nm(rng: np.random.Generator, t_s: FloatArray) -> FloatArray:
    """Drift p(t) − p(0), nm, shape (len(t), 2): settling + sinusoid + walk."""
    out = np.zeros((t_s.size, 2))
    dt = np.diff(t_s, prepend=t_s[0])
    for axis in range(2):
        amp = rng.uniform(50.0, 200.0) * rng.choice([-1.0, 1.0])
        tau = rng.uniform(1800.0, 5400.0)
        a_sin = rng.uniform(10.0, 40.0)
        period = rng.uniform(3600.0, 10800.0)
        phase = rng.uniform(0.0, 2 * np.pi)
        walk = np.cumsum(rng.normal(0.0, 0.03, t_s.size) * np.sqrt(dt))
        p = amp * (1.0 - np.exp(-t_s / tau)) + a_sin * np.sin(2 * np.pi * t_s / period + phase)
        out[:, axis] = p + walk
    out -= out[0]
    return out


def generate_track(
    *,
    size_px: int,
    seed: int,
    frames: int = 40,
    moves: bool = True,
    sample: Sample | None = None,
    snr: float = 20.0,
) -> GeneratedTrack:
    """A session of ``frames`` square frames of ``size_px`` (see the module docstring).

    Parameters
    ----------
    size_px : int
        Frame edge in px (64 or more); the frame is 1 µm across.
    seed : int
        Everything random follows from it.
    frames : int
        Number of frames (2 or more).
    moves : bool
        Three commanded offset moves, logged.
    sample : str, optional
        One of :data:`TRACK_SAMPLES`; default drawn from the seed.
    snr : float
        Height signal-to-noise ratio of each frame.
    """
    if size_px < 64:
        raise ValueError(f"size_px = {size_px} is under 64")
    if frames < 2:
        raise ValueError(f"frames = {frames} must be >= 2")
    rng = np.random.default_rng(seed)
    kind: Sample = sample if sample is not None else TRACK_SAMPLES[seed % len(TRACK_SAMPLES)]
    px_nm = FRAME_NM / size_px
    starts = np.arange(frames, dtype=np.float64) * FRAME_PERIOD_S
    mids = starts + SCAN_S / 2
    drift = _drift_nm(rng, mids)
    events: list[Event] = []
    offset = np.zeros((frames, 2))
    if moves:
        gaps = rng.choice(np.arange(1, frames), size=min(3, frames - 1), replace=False)
        for k in sorted(int(g) for g in gaps):
            move = rng.uniform(40.0, 160.0, 2) * rng.choice([-1.0, 1.0], 2)
            t_move = starts[k] - rng.uniform(10.0, FRAME_PERIOD_S - SCAN_S - 10.0)
            events.append(Event(t_s=float(t_move), kind=EventKind.OFFSET_MOVE,
                                x_nm=float(move[0]), y_nm=float(move[1])))  # fmt: skip
            offset[k:] += move
    image_nm = drift - offset  # a move of +Δ moves the content by −Δ
    image_px = image_nm / px_nm
    margin = int(np.ceil(np.abs(image_px).max())) + 8
    edge = size_px + 2 * margin
    shape = (edge, edge)
    if kind == "rough":
        tex = rough_texture(shape, pixel_size_nm=px_nm, rng=rng, rms_nm=1.0,
                            correlation_length_nm=16.0)  # fmt: skip
    elif kind == "terraces":
        tex = terrace_texture(shape, pixel_size_nm=px_nm, rng=rng, terrace_width_nm=60.0)
    else:
        tex = particle_texture(shape, pixel_size_nm=px_nm, rng=rng, diameter_nm=24.0)
    shifter = TextureShifter(tex)
    stack = np.empty((frames, size_px, size_px), np.float32)
    for k in range(frames):
        crop = shifter.crop((size_px, size_px), dx_px=image_px[k, 0], dy_px=image_px[k, 1])
        stack[k] = add_noise(crop, snr=snr, rng=rng)
    return GeneratedTrack(
        frames=stack,
        frame_times=np.column_stack([starts, starts + SCAN_S]),
        pixel_size_nm=(px_nm, px_nm),
        line_time_s=SCAN_S / size_px,
        events=events,
        truth=np.column_stack([mids, drift]),
        image_px=image_px,
        sample=kind,
        source=f"afmdrift.testing.generate_track({kind}, size_px={size_px}, seed={seed})",
    )
