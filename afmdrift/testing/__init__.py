"""Helpers for tests, demos and benchmarks: synthetic textures and exact shifts.

Runtime code (the service) never imports this package.

* Textures (periodic, nearly band-limited, heights in nm):
  :func:`particle_texture` (gold-colloid-like bumps on a flat substrate),
  :func:`terrace_texture` (graphite-like terraces with monatomic steps),
  :func:`rough_texture` (Gaussian random rough surface),
  :func:`lattice_texture` (a periodic sample: an oblique lattice of dots,
  perfect or with defects), and
  :class:`Particles` for scenes whose particles tests move or add.
* Exact shifts: :func:`fourier_shift` (periodic, sub-pixel; exact after
  :func:`band_limit`, which every texture applies) and
  :func:`shifted_crop` / :class:`TextureShifter` (shift a larger texture, cut
  a frame, so content enters and leaves at the edges as in a real scan).
* Non-rigid frames: :func:`distorted_crop` (a bowed fast axis, bowed
  lines, a small rotation, creep), :func:`distortion_field`.
* Artefacts: :func:`add_noise` (SNR = std of heights / std of noise),
  :func:`add_plane` (z offset and tilt), :func:`add_line_offsets`.
* Drift logs from a second generator, different on purpose from the
  simulator (noise processes, effect shapes, parameter ranges):
  :func:`generate_drift_log`, :func:`write_drift_log`.
* Image sessions from a second generator, different on purpose from the
  simulator (samples, rigid frames, drift shape, logged offset moves), with
  the image position registration should find: :func:`generate_track`.
* A Dask cluster of real processes on loopback for ``afmdrift batch
  --scheduler``: :class:`afmdrift.testing._dask.LoopbackDaskCluster`
  (imported from its module, so this package does not load Dask).
"""

from afmdrift.testing._driftgen import (
    DRIFTGEN_EFFECTS,
    DRIFTGEN_SHAPES,
    GeneratedLog,
    generate_drift_log,
    write_drift_log,
)
from afmdrift.testing._images import (
    DISTORTIONS,
    Particles,
    TextureShifter,
    add_line_offsets,
    add_noise,
    add_plane,
    band_limit,
    distorted_crop,
    distortion_field,
    fourier_shift,
    lattice_texture,
    particle_texture,
    rough_texture,
    shifted_crop,
    terrace_texture,
)
from afmdrift.testing._tracks import TRACK_SAMPLES, GeneratedTrack, generate_track

__all__ = [
    "DISTORTIONS",
    "DRIFTGEN_EFFECTS",
    "DRIFTGEN_SHAPES",
    "TRACK_SAMPLES",
    "GeneratedLog",
    "GeneratedTrack",
    "Particles",
    "TextureShifter",
    "add_line_offsets",
    "add_noise",
    "add_plane",
    "band_limit",
    "distorted_crop",
    "distortion_field",
    "fourier_shift",
    "generate_drift_log",
    "generate_track",
    "lattice_texture",
    "particle_texture",
    "rough_texture",
    "shifted_crop",
    "terrace_texture",
    "write_drift_log",
]
