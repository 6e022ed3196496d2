"""The simulated AFM: a virtual clock driving physics, sample and raster scanner.

Everything runs on virtual time (seconds since power-on); nothing sleeps.
:meth:`SimulatedAFM.advance_to` moves the clock forward, applies the scenario's
scheduled actions in time order, scans line after line and completes frame
after frame while scanning is on. Large jumps are fine: cost is proportional to
the pixels scanned, not to the time elapsed.

Coordinates: image coordinates ``(x, y)`` in nm from the scan window's first
pixel (x along columns, y along rows). Commanded offsets, tip moves and
manipulations are in nm; see :mod:`afmdrift.drivers.sim._scanner` for how a
pixel maps to the sample and :mod:`afmdrift.drivers.sim._physics` for p(t).
"""

from __future__ import annotations

import heapq
import logging
import math
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import numpy.typing as npt

from afmdrift._version import __version__
from afmdrift.drivers.sim._models import SimPhysics, make_physics
from afmdrift.drivers.sim._sample import Sample
from afmdrift.drivers.sim._scanner import FrameRaster, ScanGeometry, render_lines
from afmdrift.drivers.sim._scenario import (
    ControllerConfig,
    Scenario,
    check_scan_geometry,
    load_scenario,
)
from afmdrift.records import (
    ChannelSample,
    Event,
    EventKind,
    Frame,
    InstrumentInfo,
    ScanDirection,
    event_kind,
)

__all__ = ["PIEZO_RANGE_NM", "SimulatedAFM"]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

#: Default range of the simulated scanner piezo (x, y, z) in nm (the
#: scenario's ``[controller] piezo_range_nm``); the drift compensation stops
#: at a percentage of it.
PIEZO_RANGE_NM = ControllerConfig().piezo_range_nm


class SimulatedAFM:
    """A physically modelled AFM on a virtual clock.

    Parameters
    ----------
    scenario : Scenario
        Instrument, sample, physics and schedule (see :mod:`._scenario`).
    seed : int, optional
        Overrides ``scenario.seed``. The same scenario and seed give the same
        frames, channels and truth for the same sequence of calls.
    sample : Sample, optional
        Use this sample instead of the one ``scenario.sample`` describes, e.g.
        ``Sample.from_image(array, pixel_size_nm=(px, py))`` for any height image.

    Notes
    -----
    Scheduled actions of the scenario (offset moves, manipulations, tip
    changes) happen when the clock passes their time and are logged in
    :attr:`events` exactly like the same actions commanded through the API.
    Sample changes (manipulation, tip shape) take effect for scan lines whose
    trace ends after the change.
    """

    def __init__(
        self, scenario: Scenario, *, seed: int | None = None, sample: Sample | None = None
    ) -> None:
        self.scenario = scenario
        self.seed = int(scenario.seed if seed is None else seed)
        sc = scenario.scan
        self.physics: SimPhysics = make_physics(
            scenario.physics, seed=self.seed, start_offset_nm=sc.start_offset_nm
        )
        self.sample = (
            Sample.from_config(scenario.sample, seed=self.seed) if sample is None else sample
        )
        self._check_sample_extent(sc.size_nm)
        self._geometry = ScanGeometry(
            size_nm=(float(sc.size_nm[0]), float(sc.size_nm[1])),
            pixels=(int(sc.pixels[0]), int(sc.pixels[1])),
            line_rate_hz=float(sc.line_rate_hz),
            trace_fraction=float(sc.trace_fraction),
            min_frame_period_s=float(sc.frame_period_s or 0.0),
            alternate=sc.directions == "alternate",
        )
        ss = np.random.SeedSequence([self.seed, 0xA1F])
        sensor_ss, tip_ss, self._frame_ss = ss.spawn(3)
        self._rng_sensor = np.random.default_rng(sensor_ss)
        self._rng_tip = np.random.default_rng(tip_ss)
        self._t = 0.0
        self._events: list[Event] = [Event(0.0, EventKind.POWER_ON)]
        self._tip_nm = (0.0, 0.0)
        self._comp_on = False
        self._comp_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._comp_limit_pct = 10.0
        self._running = False
        self._frame: FrameRaster | None = None
        self._next_frame_start_s = 0.0
        self._frames_since_start = 0
        self._next_index = 0
        self._latest: Frame | None = None
        self._skip_before_s = -math.inf
        self._jumps: list[float] = []
        self._schedule: list[tuple[float, int, Callable[[], None]]] = []
        self._order = 0
        self._build_schedule()
        if sc.autostart:
            self.start()

    @classmethod
    def from_scenario(
        cls,
        scenario: Scenario | str | Path,
        *,
        seed: int | None = None,
        sample: Sample | None = None,
    ) -> SimulatedAFM:
        """Build from a :class:`Scenario`, a TOML path, or a built-in scenario name."""
        if not isinstance(scenario, Scenario):
            scenario = load_scenario(scenario)
        return cls(scenario, seed=seed, sample=sample)

    # ------------------------------------------------------------------ schedule

    def _push(self, t_s: float, action: Callable[[], None]) -> None:
        heapq.heappush(self._schedule, (float(t_s), self._order, action))
        self._order += 1

    def _build_schedule(self) -> None:
        sc = self.scenario
        for m in sc.offset_moves:
            self._push(m.t_s, partial(self.set_offset, m.x_nm, m.y_nm))
        tips = sc.physics.tip_changes
        if tips.enabled:
            for tc in tips.scheduled:
                self._push(
                    tc.t_s,
                    partial(self._tip_change, tc.step_nm[0], tc.step_nm[1], tc.tip_radius_nm),
                )
            if tips.rate_per_h > 0:
                self._push(self._next_spontaneous_tip(0.0), self._spontaneous_tip)
        for ev in sc.physics.events:
            self._push(ev.t_s, partial(self._log_event, ev.kind))
        for mp in sc.manipulations:
            self._push(
                mp.t_s,
                partial(
                    self._manipulate_scheduled,
                    mp.x0_nm,
                    mp.y0_nm,
                    mp.x1_nm,
                    mp.y1_nm,
                    snap=mp.snap_to_particle,
                ),
            )

    def _next_spontaneous_tip(self, after_s: float) -> float:
        rate_per_s = self.scenario.physics.tip_changes.rate_per_h / 3600.0
        return after_s + float(self._rng_tip.exponential(1.0 / rate_per_s))

    def _spontaneous_tip(self) -> None:
        sigma = self.scenario.physics.tip_changes.step_sigma_nm
        dx, dy = self._rng_tip.normal(0.0, sigma, 2)
        self._tip_change(float(dx), float(dy), None)
        self._push(self._next_spontaneous_tip(self._t), self._spontaneous_tip)

    def _tip_change(self, dx_nm: float, dy_nm: float, tip_radius_nm: float | None) -> None:
        self.physics.add_tip_change(self._t, dx_nm, dy_nm)
        self._jumps.append(self._t)
        if tip_radius_nm is not None:
            self.sample.set_tip_radius(tip_radius_nm)
        self._events.append(Event(self._t, EventKind.TIP_CHANGE))
        _log.debug("t=%.3f s: tip change, step (%.3f, %.3f) nm", self._t, dx_nm, dy_nm)

    def _log_event(self, kind: str) -> None:
        """Log an event of a kind the simulator has no action for (``[[physics.events]]``)."""
        self._events.append(Event(self._t, event_kind(kind)))

    def _manipulate_scheduled(
        self, x0_nm: float, y0_nm: float, x1_nm: float, y1_nm: float, *, snap: bool
    ) -> None:
        if snap:
            sx, sy = self.image_to_sample(x0_nm, y0_nm)
            k, _ = self.sample.nearest_particle(sx, sy)
            if k >= 0:
                dx, dy = self.sample.particle_offset(k, sx, sy)
                x0_nm, y0_nm, x1_nm, y1_nm = x0_nm + dx, y0_nm + dy, x1_nm + dx, y1_nm + dy
        self.manipulate(x0_nm, y0_nm, x1_nm, y1_nm)

    # ------------------------------------------------------------------ clock

    @property
    def now_s(self) -> float:
        """Virtual time since power-on, s."""
        return self._t

    def advance_to(self, t_s: float, *, render_all: bool = True) -> list[Frame]:
        """Run the instrument until ``t_s``; return the frames completed on the way.

        Parameters
        ----------
        t_s : float
            Target time (s since power-on), not before :attr:`now_s`.
        render_all : bool
            With ``False``, frames that a later frame completed by ``t_s``
            supersedes are not rendered (nobody can observe them through
            :meth:`latest_frame`); they still take their index, time and random
            numbers, so frames that are rendered are the same either way. Use it
            to jump far ahead cheaply.

        Raises
        ------
        ValueError
            ``t_s`` is before the current time or not finite.
        """
        t_s = float(t_s)
        if not math.isfinite(t_s) or t_s < self._t:
            raise ValueError(f"advance_to({t_s}): time must be finite and >= now ({self._t} s)")
        self._skip_before_s = -math.inf if render_all else t_s
        done: list[Frame] = []
        while self._schedule and self._schedule[0][0] <= t_s:
            t_next = max(self._schedule[0][0], self._t)
            done += self._scan_until(t_next)
            self._t = t_next
            while self._schedule and self._schedule[0][0] <= t_next:
                _, _, action = heapq.heappop(self._schedule)
                action()
        done += self._scan_until(t_s)
        self._t = t_s
        return done

    def _scan_until(self, t_s: float) -> list[Frame]:
        done: list[Frame] = []
        while self._running:
            if self._frame is None:
                if self._next_frame_start_s > t_s:
                    break
                self._frame = self._new_frame(self._next_frame_start_s)
            f = self._frame
            g = f.geometry
            if f.t_start_s + g.frame_period_s + g.scan_time_s <= self._skip_before_s:
                f.lines_done = g.pixels[1]  # superseded before anyone can see it
                self._finish_frame(f)
                continue
            due = f.lines_due(t_s)
            if due > f.lines_done:
                self._render(f, f.lines_done, due)
            if t_s < f.t_end_s:
                break
            frame = Frame(
                index=f.index,
                heights_nm=f.heights_nm,
                pixel_size_nm=f.geometry.pixel_size_nm,
                t_start_s=f.t_start_s,
                t_end_s=f.t_end_s,
                direction=f.direction,
            )
            done.append(frame)
            self._latest = frame
            self._finish_frame(f)
        return done

    def _finish_frame(self, f: FrameRaster) -> None:
        self._next_index += 1
        self._frames_since_start += 1
        self._next_frame_start_s = f.t_start_s + f.geometry.frame_period_s
        self._frame = None

    def _new_frame(self, t_start_s: float) -> FrameRaster:
        g = self._geometry
        cols, rows = g.pixels
        up = not g.alternate or self._frames_since_start % 2 == 0
        rng = np.random.default_rng(self._frame_ss.spawn(1)[0])
        art = self.scenario.artefacts
        noise = (
            art.noise_nm * rng.standard_normal((rows, cols), dtype=np.float32)
            if art.noise_nm > 0
            else np.zeros((rows, cols), dtype=np.float32)
        )
        lines = (
            rng.normal(0.0, art.line_offset_nm, rows) if art.line_offset_nm > 0 else np.zeros(rows)
        )
        return FrameRaster(
            index=self._next_index,
            geometry=g,
            t_start_s=t_start_s,
            direction=ScanDirection.UP if up else ScanDirection.DOWN,
            heights_nm=np.zeros((rows, cols), dtype=np.float64),
            noise_nm=noise,
            line_offsets_nm=lines,
        )

    def _render(self, f: FrameRaster, k0: int, k1: int) -> None:
        render_lines(
            f,
            k0,
            k1,
            physics=self.physics,
            sample=self.sample,
            artefacts=self.scenario.artefacts,
            bias_nm=self.direction_bias_nm(f.direction),
            jumps_s=np.asarray(self._jumps, dtype=np.float64),
        )

    def direction_bias_nm(self, direction: ScanDirection) -> tuple[float, float]:
        """Scan-direction bias of a frame: ``+b/2`` for up, ``−b/2`` for down frames (nm)."""
        sd = self.scenario.physics.scan_direction
        if not sd.enabled:
            return (0.0, 0.0)
        sign = 0.5 if direction is ScanDirection.UP else -0.5
        return (sign * sd.bias_nm[0], sign * sd.bias_nm[1])

    # ------------------------------------------------------------------ identity and scan

    def identify(self) -> InstrumentInfo:
        """Vendor ``afmdrift``, model ``SimulatedAFM``, serial naming scenario and seed."""
        return InstrumentInfo(
            vendor="afmdrift",
            model="SimulatedAFM",
            serial=f"sim-{self.scenario.name}-{self.seed}",
            firmware=__version__,
        )

    @property
    def scan_size_nm(self) -> tuple[float, float]:
        """Scan size (x, y), nm."""
        return self._geometry.size_nm

    @property
    def pixels(self) -> tuple[int, int]:
        """(cols, rows)."""
        return self._geometry.pixels

    @property
    def line_rate_hz(self) -> float:
        """Scan lines (trace + retrace) per second."""
        return self._geometry.line_rate_hz

    @property
    def pixel_size_nm(self) -> tuple[float, float]:
        """Pixel size (x, y), nm."""
        return self._geometry.pixel_size_nm

    @property
    def frame_period_s(self) -> float:
        """Time between frame starts while scanning, s."""
        return self._geometry.frame_period_s

    @property
    def geometry(self) -> ScanGeometry:
        """The current scan geometry and timing."""
        return self._geometry

    def configure_scan(
        self,
        *,
        size_nm: tuple[float, float] | None = None,
        pixels: tuple[int, int] | None = None,
        line_rate_hz: float | None = None,
    ) -> None:
        """Change the scan geometry; a frame in progress is abandoned and scanning restarts now.

        Raises
        ------
        ValueError
            A value is out of range (the message names it and the allowed range),
            or the scan would exceed half the sample's extent.
        """
        g = self._geometry
        new_size = g.size_nm if size_nm is None else (float(size_nm[0]), float(size_nm[1]))
        new_pixels = g.pixels if pixels is None else (int(pixels[0]), int(pixels[1]))
        new_rate = g.line_rate_hz if line_rate_hz is None else float(line_rate_hz)
        check_scan_geometry(new_size, new_pixels, new_rate)
        self._check_sample_extent(new_size)
        self._geometry = ScanGeometry(
            size_nm=new_size,
            pixels=new_pixels,
            line_rate_hz=new_rate,
            trace_fraction=g.trace_fraction,
            min_frame_period_s=g.min_frame_period_s,
            alternate=g.alternate,
        )
        if self._running:
            self._restart()

    def _check_sample_extent(self, size_nm: tuple[float, float]) -> None:
        for axis, size, ext in zip("xy", size_nm, self.sample.extent_nm, strict=True):
            if size > 0.5 * ext:
                raise ValueError(
                    f"scan size {axis} = {size} nm is more than half the sample extent "
                    f"({ext:.1f} nm)"
                )

    def _restart(self) -> None:
        self._frame = None
        self._frames_since_start = 0
        self._next_frame_start_s = self._t

    @property
    def running(self) -> bool:
        """Whether the instrument is scanning."""
        return self._running

    def start(self) -> None:
        """Start scanning now (first frame up). No effect while running."""
        if not self._running:
            self._running = True
            self._restart()

    def stop(self) -> None:
        """Stop scanning; a frame in progress is abandoned."""
        self._running = False
        self._frame = None

    def latest_frame(self) -> Frame | None:
        """The last completed frame, or ``None`` before the first."""
        return self._latest

    # ------------------------------------------------------------------ sensors and events

    def read_channels(self) -> ChannelSample:
        """Head temperature, relative humidity and the extra channels at :attr:`now_s`, with
        sensor noise."""
        t = self._t
        s = self.scenario.sensors
        temp = float(self.physics.head_temperature_c(t)) + float(
            self._rng_sensor.normal(0.0, s.temperature_noise_c)
        )
        rh = float(self.physics.humidity_pct(t)) + float(
            self._rng_sensor.normal(0.0, s.humidity_noise_pct)
        )
        values = {"temperature_c": temp, "humidity_pct": rh}
        for c in self.scenario.physics.channels:
            true = float(self.physics.channel_values(t)[c.name])
            values[c.name] = true + float(self._rng_sensor.normal(0.0, c.noise))
        return ChannelSample(t_s=t, values=values)

    def sensor_series(
        self, t_s: npt.ArrayLike, *, rng: np.random.Generator | None = None
    ) -> dict[str, FloatArray]:
        """Sensor readings at many times at once (for recording), with independent noise.

        Parameters
        ----------
        t_s : array_like, shape (n,)
        rng : numpy Generator, optional
            Noise source; default a stream derived from the seed.
        """
        t = np.asarray(t_s, dtype=np.float64)
        if rng is None:
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x5E45]))
        s = self.scenario.sensors
        out = {
            "temperature_c": self.physics.head_temperature_c(t)
            + rng.normal(0.0, s.temperature_noise_c, t.shape),
            "humidity_pct": self.physics.humidity_pct(t)
            + rng.normal(0.0, s.humidity_noise_pct, t.shape),
        }
        true = self.physics.channel_values(t)
        for c in self.scenario.physics.channels:
            out[c.name] = true[c.name] + rng.normal(0.0, c.noise, t.shape)
        return out

    @property
    def events(self) -> list[Event]:
        """The event log (a copy), in time order."""
        return list(self._events)

    # ------------------------------------------------------------------ actuation

    def set_offset(self, x_nm: float, y_nm: float) -> None:
        """Command the absolute XY scan offset (nm). Logged as ``offset_move`` with the delta.

        A move of +Δ shifts the scan window by +Δ over the sample, so features
        appear at u − Δ. The move is not drift; its creep and hysteresis are.
        """
        for name, v in (("x_nm", x_nm), ("y_nm", y_nm)):
            if not math.isfinite(v) or abs(v) > 1e6:
                raise ValueError(f"set_offset: {name} = {v} is out of range (allowed: |v| <= 1e6)")
        move = self.physics.command_offset(self._t, float(x_nm), float(y_nm))
        self._jumps.append(self._t)
        self._events.append(Event(self._t, EventKind.OFFSET_MOVE, move.dx_nm, move.dy_nm))

    def get_offset(self) -> tuple[float, float]:
        """The commanded XY offset (nm)."""
        c = self.physics.commanded_offset_at(self._t)
        return float(c[0]), float(c[1])

    def set_drift_compensation(
        self,
        *,
        on: bool | None,
        velocity_nm_per_s: tuple[float, float, float],
        limit_pct: float,
    ) -> None:
        """The controller's linear drift compensation (Nanonis ``Piezo.DriftCompSet``).

        While on, the piezo moves the scan window at ``velocity_nm_per_s``
        (x, y; z is kept and reported, not applied) until the displacement
        reaches ``limit_pct`` % of :attr:`piezo_range_nm` on an axis, where
        that axis stops (saturated). Switching it off releases the
        displacement (the window returns by it); switching it on starts from
        zero. ``on=None`` keeps the state and changes velocity and limit.

        The scenario's ``[controller]`` can make it another controller: one
        that keeps the displacement through off and on (``release =
        "keep"``), and one whose piezo applies ``drift_comp_gain`` times the
        velocity asked (while this reports the velocity asked).
        """
        for name, v in zip(("vx", "vy", "vz"), velocity_nm_per_s, strict=True):
            if not math.isfinite(v) or abs(v) > 1e4:
                raise ValueError(
                    f"drift compensation {name} = {v} nm/s is out of range (|v| <= 1e4)"
                )
        if not 0 < limit_pct <= 100:
            raise ValueError(f"saturation limit {limit_pct} % is out of range (allowed: (0, 100])")
        was_on = self._comp_on
        self._comp_on = was_on if on is None else bool(on)
        vx, vy, vz = (float(v) for v in velocity_nm_per_s)
        self._comp_velocity = (vx, vy, vz)
        self._comp_limit_pct = float(limit_pct)
        ctl = self.scenario.controller
        g = ctl.drift_comp_gain
        ramp = (g * vx, g * vy) if self._comp_on else (0.0, 0.0)
        release = was_on and not self._comp_on and ctl.release == "reset"
        self.physics.ramp_compensation(self._t, ramp, self._comp_limit_nm(), release=release)

    @property
    def piezo_range_nm(self) -> tuple[float, float, float]:
        """The piezo's range (x, y, z), nm (the scenario's ``[controller]``)."""
        r = self.scenario.controller.piezo_range_nm
        return (float(r[0]), float(r[1]), float(r[2]))

    def _comp_limit_nm(self) -> tuple[float, float]:
        f = self._comp_limit_pct / 100.0
        r = self.piezo_range_nm
        return (f * r[0], f * r[1])

    def drift_compensation(
        self,
    ) -> tuple[bool, tuple[float, float, float], tuple[bool, bool, bool], float]:
        """``(on, velocity_nm_per_s, saturated_xyz, limit_pct)`` now."""
        q = self.physics.compensation_at(self._t)
        lim = self._comp_limit_nm()
        g = self.scenario.controller.drift_comp_gain
        sat = tuple(
            self._comp_on
            and g * self._comp_velocity[k] != 0
            and abs(float(q[k])) >= lim[k] * (1 - 1e-9)
            for k in range(2)
        )
        return self._comp_on, self._comp_velocity, (sat[0], sat[1], False), self._comp_limit_pct

    def compensation_nm(self) -> tuple[float, float]:
        """Displacement the drift compensation applies now, nm."""
        q = self.physics.compensation_at(self._t)
        return float(q[0]), float(q[1])

    def tip_move(self, x_nm: float, y_nm: float) -> None:
        """Park the tip at image position (x, y) nm (no effect on the sample; not logged)."""
        for name, v in (("x_nm", x_nm), ("y_nm", y_nm)):
            if not math.isfinite(v):
                raise ValueError(f"tip_move: {name} = {v} is not finite")
        self._tip_nm = (float(x_nm), float(y_nm))

    @property
    def tip_position_nm(self) -> tuple[float, float]:
        """Where the tip was parked by :meth:`tip_move` or left by :meth:`manipulate`."""
        return self._tip_nm

    def image_to_sample(self, x_nm: float, y_nm: float) -> tuple[float, float]:
        """Sample position under image position (x, y) now, without scan-direction bias."""
        c = self.physics.scan_offset_at(self._t)
        p = self.physics.drift_at(self._t)
        return float(x_nm + c[0] - p[0]), float(y_nm + c[1] - p[1])

    def manipulate(self, x0_nm: float, y0_nm: float, x1_nm: float, y1_nm: float) -> int:
        """Push with the tip from (x0, y0) to (x1, y1) (image coordinates, nm).

        The path is mapped to the sample through the current offset and drift
        (the tip drifts with the scanner). Particles in its way are carried to
        its end. Logged as ``manipulation`` at (x0, y0). Returns the number of
        particles moved.
        """
        for name, v in (("x0_nm", x0_nm), ("y0_nm", y0_nm), ("x1_nm", x1_nm), ("y1_nm", y1_nm)):
            if not math.isfinite(v):
                raise ValueError(f"manipulate: {name} = {v} is not finite")
        a = self.image_to_sample(x0_nm, y0_nm)
        b = self.image_to_sample(x1_nm, y1_nm)
        moved = self.sample.push(a[0], a[1], b[0], b[1])
        self._tip_nm = (float(x1_nm), float(y1_nm))
        self._events.append(Event(self._t, EventKind.MANIPULATION, float(x0_nm), float(y0_nm)))
        _log.debug("t=%.3f s: manipulation moved %d particle(s)", self._t, len(moved))
        return len(moved)

    # ------------------------------------------------------------------ ground truth

    def truth_at(self, t_s: npt.ArrayLike) -> tuple[float, float] | tuple[FloatArray, FloatArray]:
        """True drift p(t) in nm: ``(x, y)`` floats for a scalar time, arrays for an array.

        Known exactly for all times; offset moves and tip changes not yet
        happened are not included. Never sent over the protocol.
        """
        p = self.physics.drift_at(t_s)
        if np.ndim(t_s) == 0:
            return float(p[0]), float(p[1])
        return p[..., 0], p[..., 1]
